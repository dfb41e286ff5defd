"""The verdict of a run, one rule for every place that judges one: the robustness
benchmark's draws, the graph's run summary and the commissioning's report.

A run is **safe** when the cart never left the safe range and no fault was raised;
**caught** when, safe, it was caught for good by a deadline and held inside a box from a
hold window on; **fast** the same with the earlier deadline and window (:class:`Criteria`).
:func:`judge` applies the rule to arrays of runs, :class:`Outcomes` holds a batch's
verdicts with what explains them.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

__all__ = ["FAILURES", "TIERS", "Criteria", "Outcomes", "judge"]

#: The benchmark's tiers, each within the one before it: a fast draw is caught, a caught
#: draw is safe.
TIERS = ("safe", "caught", "fast")
#: The kinds of failure, in the order :meth:`Outcomes.kinds` checks them. The first two
#: fail every tier; the others fail "caught" or "fast" by that tier's deadline and window.
FAILURES = ("cart left the safe range", "fault", "never caught", "caught, then lost",
            "caught for good too late", "not held")


@dataclass(frozen=True)
class Criteria:
    """The benchmark's three tiers, judged on each draw's true state over a run of
    ``run_s``:

    * **safe**: the cart inside the safe range at every sample and no fault, over the
      whole run (on the rig, the cart never meets an end stop);
    * **caught**: safe, caught for good (in the catch that lasts to the end of the run)
      by ``catch_by_s``, and held, |theta| < ``theta_rad`` and |x| < ``x_m`` at every
      sample from ``hold_from_s`` to the end;
    * **fast**: the same with ``fast_by_s`` and ``fast_hold_from_s``.

    Each argument that makes no sense is refused with a :class:`ValueError` naming it
    (with its command-line option).
    """

    run_s: float = 12.0
    catch_by_s: float = 8.0
    hold_from_s: float = 9.0
    fast_by_s: float = 3.0
    fast_hold_from_s: float = 6.0
    theta_rad: float = 0.05
    x_m: float = 0.02

    def __post_init__(self) -> None:
        names = {"run_s": "--run-s", "catch_by_s": "--catch-by", "hold_from_s": "--hold-from",
                 "fast_by_s": "--fast-by", "fast_hold_from_s": "--fast-hold-from",
                 "theta_rad": "the hold's |theta|", "x_m": "the hold's |x|"}
        for name, option in names.items():
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                shown = f"{value:g}" if isinstance(value, float) else value
                raise ValueError(f"{option} {shown}: a positive number of "
                                 f"{'s' if name.endswith('_s') else 'rad' if 'theta' in name else 'm'}")
        for by, hold, tier in (("catch_by_s", "hold_from_s", "caught"),
                               ("fast_by_s", "fast_hold_from_s", "fast")):
            deadline, window = getattr(self, by), getattr(self, hold)
            if deadline > self.run_s:
                raise ValueError(f"{names[by]} {deadline:g} s is past {names['run_s']} "
                                 f"{self.run_s:g} s: the {tier} tier's catch could never "
                                 "be seen")
            if not window < self.run_s:
                raise ValueError(f"{names[hold]} {window:g} s is not inside the run "
                                 f"({names['run_s']} {self.run_s:g} s): the {tier} tier's "
                                 "hold window would be empty")
            if window < deadline:
                raise ValueError(f"{names[hold]} {window:g} s is before {names[by]} "
                                 f"{deadline:g} s: the {tier} tier would ask for a hold "
                                 "before its catch")
        if self.fast_by_s > self.catch_by_s or self.fast_hold_from_s > self.hold_from_s:
            raise ValueError(f"the fast tier ({names['fast_by_s']} {self.fast_by_s:g} s, "
                             f"{names['fast_hold_from_s']} {self.fast_hold_from_s:g} s) must "
                             f"be within the caught tier ({names['catch_by_s']} "
                             f"{self.catch_by_s:g} s, {names['hold_from_s']} "
                             f"{self.hold_from_s:g} s)")

    def rule(self, tier: str) -> tuple[float, float]:
        """(catch deadline, start of the hold window) of the tier "caught" or "fast"."""
        if tier == "caught":
            return self.catch_by_s, self.hold_from_s
        if tier == "fast":
            return self.fast_by_s, self.fast_hold_from_s
        raise ValueError(f"tier {tier!r}: 'caught' or 'fast'")

    def describe(self) -> list[str]:
        """The tiers' rules in words, a line each."""
        box = f"|theta| < {self.theta_rad:g} rad and |x| < {self.x_m:g} m"
        return [f"safe: inside the safe range at every sample, no fault, for the whole "
                f"{self.run_s:g} s run"]+ [
                f"{tier}: safe, caught for good by {by:g} s, held ({box}) from {hold:g} s "
                f"to {self.run_s:g} s" for tier, (by, hold) in
                (("caught", self.rule("caught")), ("fast", self.rule("fast")))]


@dataclass(frozen=True)
class Outcomes:
    """Per-draw results, in draw order; the tiers' verdicts as the criteria judged them."""

    safe: np.ndarray
    caught: np.ndarray
    fast: np.ndarray
    caught_at_s: np.ndarray  # start of the catch that lasts; inf if none
    first_catch_s: np.ndarray
    largest_x_m: np.ndarray  # largest |x| over the run (true state)
    unheld_at_s: np.ndarray  # the last sample outside the hold box; -inf if none
    hold_theta_rad: np.ndarray  # largest |theta| from the caught tier's hold window on
    hold_x_m: np.ndarray
    hold_setpoint_rms_a: np.ndarray
    faulted: np.ndarray
    left_range: np.ndarray  # the true cart position left the safe range

    @staticmethod
    def concatenate(parts: Sequence[Outcomes]) -> Outcomes:
        return Outcomes(*(np.concatenate([getattr(p, f) for p in parts])
                          for f in Outcomes.__dataclass_fields__))

    def __len__(self) -> int:
        return len(self.safe)

    def passed(self, tier: str) -> np.ndarray:
        """The draws that pass ``tier`` (one of :data:`TIERS`)."""
        if tier not in TIERS:
            raise ValueError(f"tier {tier!r}: one of {', '.join(TIERS)}")
        return getattr(self, tier)

    def rates(self) -> dict[str, float]:
        """Each tier's fraction of the draws."""
        return {tier: float(np.mean(self.passed(tier))) for tier in TIERS}

    def score(self, penalty: float = 0.0, safe_target: float = 1.0) -> float:
        """One number that orders configurations safe first: one more safe draw outweighs
        any number of catches, up to ``safe_target`` of the draws (beyond it, safety is
        met and the catches decide); then each caught draw counts one and each fast draw
        one more (a fast draw is caught), less ``penalty`` counted in the same draws. At
        most 1, when every draw is fast and there is no penalty."""
        n = len(self)
        safe, caught, fast = (int(np.sum(self.passed(t))) for t in TIERS)
        enough = math.ceil(safe_target * n - 1e-9)
        weight = 2.0 * n + 1.0
        return (min(safe, enough) * weight + caught + fast - penalty) / (
            enough * weight + 2.0 * n)

    def kinds(self, criteria: Criteria, tier: str = "fast") -> np.ndarray:
        """Each draw's failure of ``tier`` as an index into :data:`FAILURES`; -1 where it
        passes. A draw that both faulted and was never caught counts as a fault."""
        never = ~np.isfinite(self.caught_at_s)
        if tier == "safe":
            return np.select([self.safe, self.left_range], [-1, 0], 1)
        by, hold = criteria.rule(tier)
        return np.select(
            [self.passed(tier), self.left_range, self.faulted,
             never & ~np.isfinite(self.first_catch_s), never, self.caught_at_s > by],
            [-1, 0, 1, 2, 3, 4], 5)

    def why(self, k: int, criteria: Criteria, tier: str = "fast") -> str:
        """In words, why draw ``k`` failed ``tier`` (empty where it passed)."""
        kind = int(self.kinds(criteria, tier)[k])
        if kind < 0:
            return ""
        if kind == 0:
            return f"cart left the safe range (|x| up to {self.largest_x_m[k]:.3f} m)"
        if kind == 3:
            return f"caught at {self.first_catch_s[k]:.2f} s, lost"
        if kind == 4:
            return f"caught for good only at {self.caught_at_s[k]:.2f} s"
        if kind == 5:
            return f"not held: outside the hold box until {self.unheld_at_s[k]:.2f} s"
        return FAILURES[kind]

    def badness(self, criteria: Criteria, tier: str = "fast") -> np.ndarray:
        """A ranking of ``tier``'s failures, worst first when sorted in descending order;
        0 where the draw passes."""
        never = ~np.isfinite(self.caught_at_s)
        if tier == "safe":
            return (~self.safe) * (1.0 + self.largest_x_m)
        by, hold = criteria.rule(tier)
        late = np.where(never, 0.0, np.maximum(self.caught_at_s - by, 0.0))
        unheld = np.where(never, 0.0, np.maximum(self.unheld_at_s - hold, 0.0))
        return (~self.passed(tier)) * (4.0 * (self.faulted | self.left_range) + 2.0 * never
                                       + np.minimum(late, 1.0) + np.minimum(unheld, 1.0))


def judge(criteria: Criteria, faulted: np.ndarray, left_range: np.ndarray,
          caught_at_s: np.ndarray, unheld_at_s: np.ndarray
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The tiers' verdicts (safe, caught, fast) of runs, each by :class:`Criteria`'s rule:
    safe, no fault and never outside the safe range; caught and fast, safe, caught for good
    (``caught_at_s``, inf if never) by the tier's deadline and no sample outside the hold
    box (the last at ``unheld_at_s``, -inf if none) from its hold window on. The one rule
    of the benchmark, the graph's run summary and the commissioning's report."""
    safe = ~np.asarray(faulted, dtype=bool) & ~np.asarray(left_range, dtype=bool)

    def tier(name: str) -> np.ndarray:
        by, hold = criteria.rule(name)
        return safe & (np.asarray(caught_at_s) <= by) & (np.asarray(unheld_at_s) < hold)

    return safe, tier("caught"), tier("fast")
