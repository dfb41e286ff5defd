"""The robustness benchmark's report (``pisc_robustness``, ``pisc_tune``,
``pisc_commission``): the distribution described, the tiers with their intervals and
failures, the fast tier over the witnessed draws, each tier's worst draws with the command
that reruns them, and the success rate by each parameter's value (:func:`plot_success`)."""

from __future__ import annotations

import textwrap
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from pisc_runs.verdict import Criteria, Outcomes
    from pisc_robust.uncertainty import Distribution, Draws

__all__ = ["describe_distribution", "percentiles", "plot_success", "report", "witness_table",
           "witnessed_report", "worst"]


def describe_distribution(distribution: Distribution) -> str:
    lines = [f"distribution {distribution.name} (digest {distribution.digest})"
             + (f": {distribution.description}" if distribution.description else "")]
    lines += [f"  {name} = {value} (fixed)" for name, value in distribution.plant.items()]
    lines += [f"  {r.describe()}" for r in distribution.ranges]
    return "\n".join(lines)


def percentiles(values: np.ndarray, unit: str, digits: int = 3) -> str:
    if values.size == 0:
        return "none"
    p5, p50, p95 = np.percentile(values, [5, 50, 95])
    return (f"p5 {p5:.{digits}f}, p50 {p50:.{digits}f}, p95 {p95:.{digits}f}, max "
            f"{np.max(values):.{digits}f} {unit}")


def report(outcomes: Outcomes, criteria: Criteria) -> list[str]:
    """The summary lines (everything but the wall time and the worst draws)."""
    from pisc_robust.robustness import binomial_interval
    from pisc_runs.verdict import FAILURES, TIERS

    n = len(outcomes)
    lines = []
    for tier in TIERS:
        wins = int(np.sum(outcomes.passed(tier)))
        low, high = binomial_interval(wins, n)
        kinds = outcomes.kinds(criteria, tier)
        counts = [(int(np.sum(kinds == k)), name) for k, name in enumerate(FAILURES)]
        failures = ", ".join(f"{name} {count}" for count, name in counts if count)
        lines.append(f"{tier:6s} {wins} of {n} = {100 * wins / n:.2f} % (95 % interval "
                     f"{100 * low:.2f} .. {100 * high:.2f} %); failures: "
                     + (failures or "none"))
    caught = outcomes.caught_at_s[np.isfinite(outcomes.caught_at_s)]
    lines.append(f"catch time ({caught.size} caught for good): {percentiles(caught, 's', 2)}")
    lines.append(f"largest |x| (all draws): {percentiles(outcomes.largest_x_m, 'm')}")
    rms = outcomes.hold_setpoint_rms_a[outcomes.caught]
    lines.append(f"hold's current set-point RMS from {criteria.hold_from_s:g} s (caught): " + (
        "none" if rms.size == 0 else
        f"median {np.median(rms):.4f} A, p95 {np.percentile(rms, 95):.4f} A"))
    return lines


def witness_table(choice: str | None, distribution: Distribution, criteria: Criteria
                  ) -> tuple[Path, dict[str, Any], np.ndarray] | None:
    """The witness table to measure the fast tier over: (path, header, witnessed mask);
    None for ``none``, or by default when none is shipped for the distribution.

    A table must be of the distribution's draws (its digest) and made with the fast
    tier's rules (catch by, held from); ValueError names what differs."""
    from pisc_analysis.witnesses import read_witness_csv
    from pisc_msgs_py.config import package_dir

    if choice == "none":
        return None
    if choice is None:
        shipped = sorted((package_dir("pisc_robust", "distributions") / "witnesses")
                         .glob(f"{distribution.name}-*.csv"))
        for path in shipped:
            meta, _ = read_witness_csv(path)
            if (meta["distribution_digest"] == distribution.digest
                    and (meta["catch_by_s"], meta["hold_from_s"])
                    == (criteria.fast_by_s, criteria.fast_hold_from_s)):
                choice = str(path)
                break
        else:
            return None
    path = Path(choice)
    if not path.is_file():
        raise ValueError(f"--witnesses {choice}: no such file")
    meta, rows = read_witness_csv(path)
    if meta["distribution_digest"] != distribution.digest:
        raise ValueError(f"--witnesses {path}: its draws are of a distribution with digest "
                         f"{meta['distribution_digest']}, not {distribution.name}'s "
                         f"{distribution.digest}")
    rules = (meta["catch_by_s"], meta["hold_from_s"])
    if rules != (criteria.fast_by_s, criteria.fast_hold_from_s):
        raise ValueError(f"--witnesses {path}: made for a catch by {rules[0]:g} s held from "
                         f"{rules[1]:g} s, not the fast tier's {criteria.fast_by_s:g} s and "
                         f"{criteria.fast_hold_from_s:g} s")
    if meta["searched"] != meta["draws"]:
        raise ValueError(f"--witnesses {path}: searched {meta['searched']} of its "
                         f"{meta['draws']} draws; the fast tier is measured over all of them")
    witnessed = np.zeros(meta["draws"], dtype=bool)
    for row in rows:
        witnessed[row["draw"]] = row["feasible"]
    return path, meta, witnessed


def witnessed_report(outcomes: Outcomes, witnessed: np.ndarray, source: str) -> list[str]:
    """The fast tier over the draws a feasibility study found a witness for."""
    from pisc_robust.robustness import binomial_interval

    n = int(np.sum(witnessed))
    wins = int(np.sum(outcomes.fast & witnessed))
    if n == 0:
        return [f"fast over witnessed draws: {source} has no witness"]
    low, high = binomial_interval(wins, n)
    return [f"fast over the {n} witnessed of {len(outcomes)} draws ({source}): {wins} = "
            f"{100 * wins / n:.2f} % (95 % interval {100 * low:.2f} .. {100 * high:.2f} %); "
            f"safe {int(np.sum(outcomes.safe))} of {len(outcomes)}, fast over all "
            f"{int(np.sum(outcomes.fast))}"]


def worst(outcomes: Outcomes, criteria: Criteria, draws: Draws, distribution: Distribution,
          config: str, overrides: dict[str, Any], k: int) -> list[str]:
    """Each tier's ``k`` worst failures among the draws that pass the tiers before it,
    each with its values and the command that reruns it."""
    from pisc_robust.robustness import rerun_command
    from pisc_runs.verdict import TIERS

    lines = []
    below = np.ones(len(outcomes), dtype=bool)
    for tier in TIERS:
        badness = outcomes.badness(criteria, tier) * below
        order = [int(i) for i in np.argsort(-badness, kind="stable")[:k] if badness[i] > 0]
        below = below & outcomes.passed(tier)
        if not k:
            continue
        if not order:
            lines.append(f"worst draws, {tier}: no failure")
            continue
        lines.append(f"worst {len(order)} draws, {tier} (the graph draws its own "
                     "measurement noise):")
        for i in order:
            values = {name: float(f"{v:.6g}") for name, v in draws.one(i).items()}
            lines.append(f"  draw {i}: {outcomes.why(i, criteria, tier)}")
            lines += textwrap.wrap(", ".join(f"{name}={v:g}" for name, v in values.items()),
                                   width=100, initial_indent="    ", subsequent_indent="    ",
                                   break_on_hyphens=False)
            lines.append("    " + rerun_command(config, overrides, distribution.plant, values))
    return lines


def plot_success(path: Path, distribution: Distribution, draws: Draws, outcomes: Outcomes,
                 title: str) -> None:
    """Success rate in 10 bins of each varied parameter's value, one panel each."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FixedLocator, FuncFormatter, MaxNLocator, NullFormatter

    from pisc_robust.robustness import success_by_value
    from pisc_robust.uncertainty import unit_of

    from pisc_runs.verdict import TIERS

    ranges = distribution.ranges
    columns = 4
    rows = -(-len(ranges) // columns)
    fig, axes = plt.subplots(rows, columns, figsize=(3.3 * columns, 2.2 * rows + 0.9),
                             sharey=True, squeeze=False)
    rates = outcomes.rates()
    short = FuncFormatter(lambda v, _: f"{v:.3g}")
    for ax, r in zip(axes.flat, ranges, strict=False):
        log = r.kind == "factor"
        for color, tier in zip(("C2", "C0", "C1"), TIERS, strict=True):
            edges, rate, count = success_by_value(draws.values[r.name], outcomes.passed(tier),
                                                  log=log, span=r.value_range)
            percent = 100 * np.nan_to_num(rate)
            ax.stairs(percent, edges, color=color, lw=1.2, label=tier)
        if log:  # factor ranges: log axis, ticks at the ends and the nominal value
            ax.set_xscale("log")
            ax.xaxis.set_major_locator(FixedLocator([*r.value_range, r.nominal]))
            ax.xaxis.set_minor_formatter(NullFormatter())
        else:
            ax.xaxis.set_major_locator(MaxNLocator(4))
        ax.xaxis.set_major_formatter(short)
        ax.set_xlim(edges[0], edges[-1])
        unit = unit_of(r.name)
        ax.set_xlabel(r.name + (f" [{unit}]" if unit else ""), fontsize=8)
        ax.tick_params(labelsize=7)
        ax.set_ylim(0, 102)
        ax.set_yticks([0, 25, 50, 75, 100])
        ax.grid(alpha=0.3)
    axes.flat[0].legend(fontsize=7, loc="lower left")
    for ax in axes[:, 0]:
        ax.set_ylabel("draws passing [%]", fontsize=8)
    for ax in list(axes.flat)[len(ranges):]:
        ax.set_visible(False)
    overall = ", ".join(f"{tier} {100 * rates[tier]:.1f} %" for tier in TIERS)
    fig.suptitle(f"{title}\neach tier in 10 bins of each parameter's value; all draws: "
                 f"{overall}", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)

