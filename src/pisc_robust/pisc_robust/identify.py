"""System identification from recorded runs: the rig's parameters, with their uncertainty.

The plant of :mod:`pisc_plant.plant` (the rig's full-fidelity layout: armature current,
RC-filtered sensors) is driven by the voltages a run recorded, and the parameters asked
for are fitted by ``scipy.optimize.least_squares`` so that what it predicts matches
what the sensors measured: the IR position and the current through their 10-bit ADC,
the angle through the encoder. Residuals are taken where the sensors quantise, in
their own steps (ADC codes, encoder counts; a measured code stands for the middle of
its step), so the fit's residual reads directly against the sensors' resolution:
quantisation alone gives 1/sqrt(12) = 0.29 of a step.

**Segments** (multiple shooting, :mod:`pisc_robust.identify_segments`): the recording is
cut into segments, each simulated from an initial state of its own that the fit estimates
with the parameters; what the model cannot follow is left out, and the report says so.

**Timing** (:mod:`pisc_robust.identify_data`): each voltage acts from the time it reached
the rig, from the latency the bag records plus a constant the fit can estimate
(``delay``); on the wall clock, each cycle's delay is then refined from the current
sensor (:meth:`pisc_robust.identify_model.Problem.timing`).

**The Jacobian** is one batched call of the compiled kernel: a plant set
(:func:`pisc_plant.plant_config.plant_set`) with one rig per segment and per perturbation
(each parameter, each component of a segment's initial state), forward differences.

**Stopping.** Each pass of ``least_squares`` ends as usual (on the cost, the step or
the gradient), once the next Gauss-Newton step would move every unknown by less than
a hundredth of its standard error
(:func:`pisc_robust.identify_stats.within_standard_error`), or once five iterations
together gained less than a move of a quarter standard error would
(:func:`pisc_robust.identify_stats.stalled`): along the R-J_m valley the cost keeps
falling by parts in 10^9 an evaluation, which the data cannot tell from nothing, and
such fits used to run out of evaluations.

**Uncertainty.** The 95 % intervals come from the Jacobian at the optimum, with a
cluster-robust (sandwich) covariance over segments: the quantisation error of a slowly
moving signal is far from white, and the sandwich does not assume it is; the t
quantile has one degree of freedom less than there are segments. Channels are weighted
by their residual RMS (a second pass after a first fit weighted by the sensors'
resolution). A parameter whose interval is wider than its own value (or its typical
size) is reported as not identifiable from these data and held at its base value; a
pair whose estimates correlate beyond 0.95 is named.

Some parameters cannot be told apart by any data from this model: J_m / r^2 adds to
the cart's mass M + m (fit J_m with M known, or M with J_m known), b_m / r^2 to the
cart's viscous friction, and L acts only within 0.14 ms of a voltage step, as a delay
would. The correlation warning names such pairs when both are fitted.
"""

from __future__ import annotations


from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import stats
from scipy.optimize import least_squares

from pisc_plant.plant_config import PlantConfig
from pisc_robust.identify_data import (
    BY_KEY,
    NOT_PLANT,
    UNKNOWNS,
    FitError,
    IdentifyError,
    Recording,
    Unknown,
)
from pisc_robust.identify_model import Problem, config_value, model_plant
from pisc_robust.identify_segments import Segments, make_segments
from pisc_robust.identify_stats import (
    STALL_FRACTION,
    STALL_ITERATIONS,
    STOP_FRACTION,
    covariance,
    inseparable,
    stalled,
    within_standard_error,
)

__all__ = ["IDENTIFIABLE", "OUTLIER", "TIMING_ROUNDS", "Estimate", "Result", "identify"]

#: An estimate is reported as identified when its 95 % interval's half-width is at most
#: this fraction of it (or a tenth of the parameter's typical size, for a value near 0)
IDENTIFIABLE = 0.25
#: Passes of the per-cycle timing for a run on the wall clock (each a fit of its own)
TIMING_ROUNDS = 2
#: A segment whose residual RMS exceeds this many times the median segment's is left out
OUTLIER = 4.0


@dataclass(frozen=True)
class Estimate:
    unknown: Unknown
    value: float
    low: float  # 95 % interval
    high: float
    std: float
    base: float
    identifiable: bool = True
    reason: str = ""  # why it is not identifiable, when it is not fitted at all

    @property
    def half_width(self) -> float:
        return 0.5 * (self.high - self.low)


@dataclass
class Result:
    estimates: list[Estimate]
    not_identifiable: list[Estimate]
    correlation: np.ndarray  # of every fitted parameter (``fitted``)
    warnings: list[str]
    residual_rms: np.ndarray  # per channel, in sensor steps
    segments: Segments
    recordings: list[Recording]
    predicted: np.ndarray  # (n, length, 3)
    base: PlantConfig
    iterations: int
    wall_s: float
    cycles: int
    delay_s: float  # the constant part of the sample-to-voltage time used
    timing_spread_s: float | None = None  # each cycle's delay about it (wall clock)
    fitted: list[Estimate] = field(default_factory=list)  # every parameter fitted, in order

    def value(self, key: str) -> float | None:
        return next((e.value for e in self.estimates if e.unknown.key == key), None)



def _drop_outliers(problem: Problem, segments: Segments, z: np.ndarray,
                   recordings: Sequence[Recording], say: Callable[[str], None]
                   ) -> tuple[Problem, Segments]:
    """Leave out the segments the fitted model cannot follow at all (a voltage that was
    recorded but never reached the motor: a driver holding 0 V at the start of a run,
    or after a watchdog; a knock on the cart): their residual RMS is more than
    :data:`OUTLIER` times the median segment's."""
    r = problem.solve_states(z)
    counts = np.maximum(segments.mask.reshape(segments.count, -1).sum(axis=1), 1)
    rms = np.sqrt(np.einsum("ij,ij->i", r, r) / counts)
    keep = rms <= OUTLIER * max(float(np.median(rms)), 1.0)
    if keep.all() or keep.sum() < 2:
        return problem, segments
    say(f"leaving out {int((~keep).sum())} segment(s) the model cannot follow")
    offsets = problem.offsets[keep]
    weights = problem.weights
    segments = segments.subset(
        keep, "the model cannot follow it (residual over "
        f"{OUTLIER:g} times the median segment's): was the recorded voltage applied?",
        recordings)
    new = Problem(segments, problem.base_config, problem.fit, problem.start)
    new.offsets = offsets
    new.weights = weights
    new.simulations = problem.simulations
    return new, segments



def identify(recordings: Sequence[Recording], fit: Sequence[Unknown], base: PlantConfig,
             segment_s: float = 1.0, max_evaluations: int = 100,
             progress: Callable[[str], None] | None = None,
             timing_rounds: int = TIMING_ROUNDS,
             on_evaluation: Callable[[int, int, int], None] | None = None) -> Result:
    """Fit ``fit`` to the recordings, from ``base``'s values; see the module's notes.

    ``progress`` receives a line of text per pass; ``on_evaluation(pass, passes,
    evaluations)`` is called after every evaluation of the residuals (``pass`` counts
    from 0, ``evaluations`` within the pass): a progress bar's hook.

    Raises :class:`IdentifyError` for input that cannot serve (no voltage to excite what
    is asked, no usable segment) and :class:`FitError` when the fit fails.
    """
    started = time.perf_counter()
    say = progress or (lambda text: None)
    _check_excited(recordings, fit, base)
    segments = make_segments(recordings, base.sensors, base.loop.period_s, segment_s)
    fitted, unfitted = _separable(fit, base)
    problem = Problem(segments, base, fitted, _start_values(base, fit))
    low, high = problem.bounds()
    z = np.clip(problem.initial(), low, high)
    rounds = timing_rounds if any(r.wall_clock for r in recordings) else 0
    passes = _Passes(2 + rounds, max_evaluations, say, on_evaluation, started)

    z = passes.solve(problem, z, "weights: the sensors' resolution")
    problem, segments = _drop_outliers(problem, segments, z, recordings, say)
    problem.reweight(z)
    z = passes.solve(problem, z, "weights: the residuals")
    timing_spread: float | None = None
    for _ in range(rounds):
        change, spread = problem.timing(z)
        segments.latency += change
        timing_spread = spread
        problem.forget()
        problem.reweight(z)
        z = passes.solve(problem, z, f"each cycle's delay from the current: spread "
                         f"{spread * 1e3:.2f} ms")
    estimates, correlation, warnings = _estimates(problem, z, fitted, base)
    values = problem.values(z)
    rms = problem.channel_rms(z)
    cycles = sum(len(rec.stamps_ns) for rec in recordings)
    return Result([e for e in estimates if e.identifiable],
                  unfitted + [e for e in estimates if not e.identifiable], correlation,
                  warnings, rms,
                  segments, list(recordings), problem.predictions(z), base, passes.evaluations,
                  time.perf_counter() - started, cycles, float(values["delay"]),
                  timing_spread_s=timing_spread, fitted=estimates)


def _check_excited(recordings: Sequence[Recording], fit: Sequence[Unknown],
                   base: PlantConfig) -> None:
    """:class:`IdentifyError` when there is no recording, or when what is asked is seen
    only through the motor and the recorded voltage is zero throughout."""
    if not recordings:
        raise IdentifyError("no recording to identify from")
    step_v = base.actuator.step_v or 1e-3
    needs = [u for u in fit if u.needs_voltage and u.key not in NOT_PLANT]
    if needs and all(np.all(np.abs(r.voltage) < 0.5 * step_v) for r in recordings):
        raise IdentifyError(
            "the recorded voltage is zero throughout: nothing excites the motor and the cart, "
            f"so {', '.join(u.key for u in needs)} cannot be identified (record an "
            "excitation experiment: experiment.kind: excitation)")


def _start_values(base: PlantConfig, fit: Sequence[Unknown]) -> dict[str, float]:
    """Every unknown's value to start from: the model's, the delay's and a zero current
    offset; a fitted one at or below its lower bound (or at 0) moved inside the bounds."""
    model = model_plant(base)
    start = {u.key: config_value(model, u.name) for u in UNKNOWNS if u.key not in NOT_PLANT}
    start["delay"] = base.actuator.command_delay_s
    start["current_offset"] = 0.0
    for u in fit:
        if u.key == "current_offset":
            continue
        if start[u.key] <= u.low or (u.key != "delay" and start[u.key] == 0.0):
            start[u.key] = u.low + 0.2 * u.scale  # inside the bounds: the fit can move it
    return start


def _separable(fit: Sequence[Unknown], base: PlantConfig
               ) -> tuple[list[Unknown], list[Estimate]]:
    """(the unknowns to fit, those set aside as not identifiable, with the reason)."""
    fitted = list(fit)
    unfitted: list[Estimate] = []
    keys = [u.key for u in fitted]
    period = base.loop.period_s
    if "L" in keys and "delay" in keys:
        # L shapes the current only within a few L / R of each voltage step, as a delay
        # of L / R would: with each command's delay unknown to that precision (fitted),
        # no sampling at 5 ms tells the two apart (the fit would trade them freely)
        L = BY_KEY["L"]
        b = _base_value(base, L)
        unfitted.append(Estimate(
            L, b, math.nan, math.nan, math.nan, b, False,
            f"at {period * 1e3:g} ms sampling L acts only as a delay of L / R "
            f"({b / base.motor.resistance_ohm * 1e3:.2f} ms at the base values) would, and the "
            "delay of the commands is not known to that precision: fitted with it, the two "
            "cannot be told apart"))
        fitted = [u for u in fitted if u.key != "L"]
    return fitted, unfitted


class _Passes:
    """The fit's passes of ``least_squares``, counted for the progress hooks."""

    def __init__(self, passes: int, max_evaluations: int, say: Callable[[str], None],
                 on_evaluation: Callable[[int, int, int], None] | None,
                 started: float) -> None:
        self.passes = passes
        self.max_evaluations = max_evaluations
        self.say = say
        self.on_evaluation = on_evaluation
        self.started = started
        self.done = 0
        self.evaluations = 0

    def solve(self, problem: Problem, z: np.ndarray, what: str) -> np.ndarray:
        """One pass from ``z``: the parameters it ends at; :class:`FitError` when it does
        not converge within ``max_evaluations``."""
        low, high = problem.bounds()
        self.say(f"fitting {', '.join(u.key for u in problem.fit)} over {problem.seg.count} "
                 f"segments ({what})")
        count = 0

        def residuals(z: np.ndarray) -> np.ndarray:
            nonlocal count
            out = problem.residuals(z)
            count += 1
            if self.on_evaluation is not None:
                self.on_evaluation(self.done, self.passes, count)
            return out

        last_jacobian: list[tuple[bytes, np.ndarray]] = []

        def jacobian(z: np.ndarray) -> np.ndarray:
            j = problem.jacobian(z)
            last_jacobian[:] = [(np.asarray(z, dtype=float).tobytes(), j)]
            return j

        costs: list[float] = []
        stalled_here = False

        def close_enough(intermediate_result: Any) -> None:
            # (least_squares passes its OptimizeResult to a parameter of this name only)
            nonlocal stalled_here
            x = np.asarray(intermediate_result.x, dtype=float)
            r = intermediate_result.fun
            costs.append(float(r @ r))
            if stalled(costs, len(r) - len(x)):
                stalled_here = True
                raise StopIteration
            # the iterate least_squares just accepted has its Jacobian computed
            if not last_jacobian or last_jacobian[0][0] != x.tobytes():
                return
            if within_standard_error(last_jacobian[0][1], r, x, low, high):
                raise StopIteration

        try:
            solution = least_squares(
                residuals, z, jac=jacobian, bounds=(low, high),
                method="trf", x_scale="jac", ftol=1e-9, xtol=1e-9, gtol=1e-9,
                max_nfev=self.max_evaluations, callback=close_enough)
        except IdentifyError:
            raise
        except (ValueError, np.linalg.LinAlgError) as exc:
            raise FitError(f"the fit failed: {exc}") from None
        self.evaluations += solution.nfev
        why = {-2: (f"{STALL_ITERATIONS} iterations gained less than a move of "
                    f"{STALL_FRACTION:g} of a standard error" if stalled_here else
                    f"the next step under {STOP_FRACTION:g} of a standard error"),
               1: "gradient", 2: "cost", 3: "step", 4: "cost and step"}.get(solution.status)
        self.say(f"  {solution.nfev} evaluations, {solution.njev} Jacobians, "
                 f"{problem.simulations} simulations, "
                 f"{time.perf_counter() - self.started:.1f} s"
                 + (f"; converged ({why})" if why else ""))
        if solution.status == 0 or solution.status == -1:
            raise FitError(
                f"the fit did not converge within {self.max_evaluations} evaluations "
                f"({solution.message.rstrip('.')})" + inseparable(problem, solution.x))
        self.done += 1
        return solution.x


def _estimates(problem: Problem, z: np.ndarray, fitted: Sequence[Unknown],
               base: PlantConfig) -> tuple[list[Estimate], np.ndarray, list[str]]:
    """Each fitted parameter's estimate with its 95 % interval (the cluster-robust
    covariance's, t quantile), their correlation, and a warning per pair correlated
    beyond 0.95."""
    r = problem.residuals(z)
    jac = problem.jacobian(z)
    cov, dof = covariance(problem, jac, r)
    t = float(stats.t.ppf(0.975, dof))
    values = problem.values(z)
    std = np.sqrt(np.maximum(np.diag(cov), 0.0)) * problem.scale
    estimates = []
    for k, u in enumerate(fitted):
        v = values[u.key]
        half = t * std[k]
        estimates.append(Estimate(u, v, max(v - half, u.low), min(v + half, u.high),
                                  float(std[k]), _base_value(base, u),
                                  half <= max(IDENTIFIABLE * abs(v), 0.1 * u.scale)))
    scale = problem.scale
    cov_phys = cov * np.outer(scale, scale)
    d = np.sqrt(np.maximum(np.diag(cov_phys), 1e-300))
    correlation = cov_phys / np.outer(d, d)
    warnings = []
    for a in range(len(estimates)):
        for b in range(a + 1, len(estimates)):
            c = correlation[a, b]
            if abs(c) > 0.95:
                warnings.append(
                    f"{estimates[a].unknown.key} and {estimates[b].unknown.key}: correlation "
                    f"{c:+.3f}: these data cannot tell them apart (fix one of them)")
    return estimates, correlation, warnings


def _base_value(base: PlantConfig, u: Unknown) -> float:
    return 0.0 if u.key == "current_offset" else config_value(base, u.name)
