"""The commissioning's last stages: verification on fresh draws, the report and the tuned
file with its provenance (:mod:`pisc_robust.commission`).

``verify`` runs the configuration the commissioning started from (``rig.yaml``) and the
tuned one on the same fresh draws of the rig's distribution (seed: the commissioning's
plus :data:`VERIFY_SEED_OFFSET`, so none is a tuning draw) and judges them by the
benchmark's tiers (:class:`~pisc_runs.verdict.Criteria`, the rule the graph's run
summary and ``pisc_robustness`` use), with Clopper-Pearson intervals; it plots each tier's
success against every varied parameter and the distribution of the catch time.

``report`` writes ``DIR/report.md`` (the runs, the identification, the distribution, the
tuning, the verification, each with its plots) and ``DIR/tuned.yaml``: the tuned
configuration headed by its provenance, every input named: the bags with their digests,
the seeds, the configuration, distribution and space with their digests, the commands
and the versions of PISC and of the libraries that made it.
"""

from __future__ import annotations

import hashlib
import json
import platform
import subprocess
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["VERIFY_SEED_OFFSET", "plot_catch_times", "plot_residuals", "report",
           "verify", "versions"]

#: The verification's draws come from the commissioning's seed plus this
VERIFY_SEED_OFFSET = 1000
LIBRARIES = ("numpy", "scipy", "numba", "optuna", "dask", "distributed", "matplotlib",
             "control", "mcap", "PyYAML")


def plot_residuals(results: Mapping[str, Any], path: Path) -> None:
    """Each fit's residuals in sensor steps, a histogram per channel and fit, beside what
    quantisation alone gives (a uniform error over one step)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from pisc_robust.identify_data import CHANNELS, QUANTISATION_RMS

    fig, axes = plt.subplots(len(results), 3, figsize=(11, 2.6 * len(results)),
                             squeeze=False)
    for row, (stage, result) in enumerate(results.items()):
        s = result.base.sensors
        steps = np.array([s.adc_lsb_v, s.encoder_rad_per_count, s.adc_lsb_v])
        seg = result.segments
        parts = [(result.predicted[n, :seg.size[n]] - seg.measured[n, :seg.size[n]]) / steps
                 for n in range(seg.count)]
        residual = np.concatenate(parts) if parts else np.zeros((0, 3))
        for c, name in enumerate(CHANNELS):
            ax = axes[row, c]
            values = residual[:, c]
            ax.hist(values, bins=np.linspace(-4, 4, 81), color=f"C{c}", alpha=0.8)
            ax.set_title(f"{stage}: {name}\nRMS {result.residual_rms[c]:.3f} steps "
                         f"(quantisation {QUANTISATION_RMS:.3f})", fontsize=9)
            ax.set_xlabel("residual [sensor steps]", fontsize=8)
            ax.tick_params(labelsize=7)
            ax.grid(alpha=0.3)
    fig.suptitle("The identified model against the recordings: residuals, simulated minus "
                 "measured, each segment from its fitted start", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def plot_catch_times(path: Path, outcomes: Mapping[str, Any], criteria: Any,
                     title: str) -> None:
    """The expected catch time: for each configuration the fraction of the draws caught
    for good by t, against t, with the tiers' deadlines."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    t = np.linspace(0.0, criteria.run_s, 601)
    for color, (label, o) in zip(("C7", "C0"), outcomes.items(), strict=False):
        caught = np.sort(o.caught_at_s[np.isfinite(o.caught_at_s)])
        share = np.searchsorted(caught, t, side="right") / len(o)
        finite = caught.size
        median = f"median {np.median(caught):.2f} s" if finite else "none caught"
        ax.plot(t, 100 * share, color=color, label=f"{label} ({median})")
    for by, name in ((criteria.fast_by_s, "fast"), (criteria.catch_by_s, "caught")):
        ax.axvline(by, color="0.5", ls="--", lw=0.8)
        ax.text(by, 2, f" {name} by {by:g} s", fontsize=8, color="0.3")
    ax.set_xlabel("time from the start [s]")
    ax.set_ylabel("draws caught for good [%]")
    ax.set_ylim(0, 102)
    ax.grid(alpha=0.3)
    ax.legend(loc="center right", fontsize=8)
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def verify(ctx: Any, where: Path) -> dict[str, Any]:
    """The commissioning's stage ``verify`` (module docstring)."""
    from pisc_robust.cluster import chunk_runner, workers_for
    from pisc_robust.robustness import CHUNK_DRAWS, binomial_interval, evaluate, prepare
    from pisc_runs.verdict import FAILURES, TIERS, Criteria
    from pisc_robust.robustness_report import plot_success
    from pisc_robust.uncertainty import load_distribution
    from pisc_sim.configuration import load_graph_config

    plan = ctx.plan
    files = {"start": ctx.dir("identify") / "rig.yaml", "tuned": ctx.dir("tune") / "tuned.yaml"}
    criteria = Criteria()
    seed = plan.seed + VERIFY_SEED_OFFSET
    path = ctx.dir("distribution") / "rig-distribution.yaml"
    distribution = load_distribution(str(path), load_graph_config(str(files["start"]))[0])
    draws = distribution.draw(plan.verify_draws, seed)
    chunks = -(-plan.verify_draws // CHUNK_DRAWS)
    workers = workers_for(chunks, plan.workers, plan.scheduler)
    outcomes, tiers = {}, {}
    with chunk_runner(workers, plan.scheduler) as map_chunks:
        for label, file in files.items():
            config, plant = prepare(load_graph_config(str(file))[0], distribution)
            o = evaluate(config, plant, draws, criteria, seed, map_chunks)
            outcomes[label] = o
            tiers[label] = {}
            for tier in TIERS:
                wins = int(np.sum(o.passed(tier)))
                low, high = binomial_interval(wins, len(o))
                kinds = o.kinds(criteria, tier)
                failures = {FAILURES[k]: int(np.sum(kinds == k)) for k in range(len(FAILURES))
                            if np.any(kinds == k)}
                tiers[label][tier] = {"passed": wins, "of": len(o), "low": low, "high": high,
                                      "failures": failures}
            ctx.say(f"    {label}: " + ", ".join(
                f"{t} {100 * v['passed'] / v['of']:.2f} % ({100 * v['low']:.2f} .. "
                f"{100 * v['high']:.2f})" for t, v in tiers[label].items()))
    np.savez_compressed(where / "outcomes.npz", **{
        f"{label}_{name}": getattr(o, name) for label, o in outcomes.items()
        for name in ("safe", "caught", "fast", "caught_at_s", "largest_x_m")},
        **{f"draw_{k}": v for k, v in draws.values.items()})
    plot_success(where / "success_by_parameter.png", distribution, draws, outcomes["tuned"],
                 f"the tuned configuration on {plan.verify_draws} fresh draws of the rig's "
                 f"distribution (seed {seed})")
    plot_catch_times(where / "catch_time.png", outcomes, criteria,
                     f"catch time on {plan.verify_draws} fresh draws (seed {seed}); the "
                     "configuration before and after tuning")
    caught = outcomes["tuned"].caught_at_s
    finite = caught[np.isfinite(caught)]
    return {"seed": seed, "draws": plan.verify_draws, "tiers": tiers,
            "rules": criteria.describe(),
            "catch_time_s": ({"median": float(np.median(finite)),
                              "p95": float(np.percentile(finite, 95))} if finite.size else {}),
            "plots": ["success_by_parameter.png", "catch_time.png"]}


def versions() -> dict[str, str]:
    """PISC's source (its git commit, and whether the tree had changes) and the versions
    of Python and of the libraries that made the result."""
    from importlib import metadata

    here = Path(__file__).resolve().parent
    try:
        commit = subprocess.run(["git", "-C", str(here), "rev-parse", "HEAD"],
                                capture_output=True, text=True, timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(here), "status", "--porcelain", "--",
                                str(here.parents[2])], capture_output=True, text=True,
                               timeout=10).stdout.strip()
        pisc = f"{commit}{' with uncommitted changes' if dirty else ''}" if commit else ""
    except (OSError, subprocess.SubprocessError):
        pisc = ""
    out = {"pisc": pisc or f"pisc_bringup {metadata.version('pisc_bringup')} (no git)",
           "python": platform.python_version()}
    for name in LIBRARIES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            pass
    return out


def _inputs(ctx: Any) -> list[str]:
    """Every input of the tuned file, a line each."""
    from pisc_sim.configuration import config_path

    plan, rec = ctx.plan, ctx.records
    config_digest = _digest(config_path(plan.config))
    lines = [f"rig: {plan.rig.describe()}"
             + (f" (plant digest {plan.rig.key()['plant_digest']})"
                if plan.rig.kind != "driver" else ""),
             f"configuration: {plan.config} (digest {config_digest})"
             + "".join(f" --set {k}={v}" for k, v in plan.overrides.items())]
    for stage in ("excitation", "free-swing"):
        out = rec[stage]["outputs"]
        lines.append(f"{stage} bag: {ctx.dir(stage) / out['bag']} ("
                     + ", ".join(f"{n} {d}" for n, d in out["bag_files"].items())
                     + f"), recorded {rec[stage]['made']}")
    tune = rec["tune"]["outputs"]
    lines += [
        f"distribution: {ctx.dir('distribution') / 'rig-distribution.yaml'} (digest "
        f"{rec['distribution']['outputs']['digest']}), prior {plan.prior}, widened "
        f"x{plan.widen:g}",
        f"space: {tune['space']} (digest {tune['space_digest']})",
        f"tuning: {plan.trials} trials x {plan.draws} draws, seed {plan.seed}, sampler "
        f"{plan.sampler}, study {ctx.dir('tune') / tune['storage']}",
        f"verification: {plan.verify_draws} fresh draws, seed {rec['verify']['outputs']['seed']}",
    ]
    lines += [f"version {k}: {v}" for k, v in versions().items()]
    log = plan.directory / "commands.log"
    if log.is_file():
        lines += [f"run: {line}" for line in log.read_text().splitlines()]
    return lines


def digest_files(paths: list[Path]) -> dict[str, str]:
    """The SHA-256 (first 16 hex digits) of each file, by name: what identifies an input."""
    out = {}
    for path in paths:
        h = hashlib.sha256()
        with open(path, "rb") as stream:
            for block in iter(lambda: stream.read(1 << 20), b""):
                h.update(block)
        out[path.name] = h.hexdigest()[:16]
    return out


def _digest(path: Path) -> str:
    return digest_files([path])[path.name]


def _table(tiers: Mapping[str, Any]) -> list[str]:
    from pisc_runs.verdict import TIERS

    rows = ["| configuration | " + " | ".join(TIERS) + " |",
            "|---|" + "---|" * len(TIERS)]
    for label, t in tiers.items():
        rows.append(f"| {label} | " + " | ".join(
            f"{100 * t[x]['passed'] / t[x]['of']:.2f} % ({100 * t[x]['low']:.2f} .. "
            f"{100 * t[x]['high']:.2f})" for x in TIERS) + " |")
    return rows


def report(ctx: Any, where: Path) -> dict[str, Any]:
    """The commissioning's stage ``report`` (module docstring)."""
    from pisc_runs.verdict import TIERS

    plan, rec = ctx.plan, ctx.records
    top = plan.directory
    inputs = _inputs(ctx)
    tuned_text = (ctx.dir("tune") / "tuned.yaml").read_text()
    head = ["pisc_commission: the configuration tuned for this rig; every input:"]
    tuned = top / "tuned.yaml"
    tuned.write_text("".join(f"# {line}\n" for line in head + inputs) + tuned_text)
    identified = json.loads((ctx.dir("identify") / "identified.json").read_text())
    verify_out = rec["verify"]["outputs"]
    result = rec["tune"]["outputs"]["result"]

    def rel(stage: str, name: str) -> str:
        return str((ctx.dir(stage) / name).relative_to(top))

    md = [f"# Commissioning of {plan.rig.describe()}", "",
          f"Tuned configuration: `{tuned.name}` (its header names every input). Made in "
          f"`{top}`, stage by stage; the records are each stage's `stage.json`.", "",
          "## Runs", ""]
    for stage in ("excitation", "free-swing"):
        out = rec[stage]["outputs"]
        md.append(f"- {stage}: `{rel(stage, out['bag'])}`: {out['said']}")
    md += ["", "## Identification", "",
           "| parameter | estimate | 95 % interval | from | in the file |", "|---|---|---|---|---|"]
    for e in identified["estimates"]:
        md.append(f"| {e['name']} | {e['value']:.6g} {e['unit']} | {e['low']:.6g} .. "
                  f"{e['high']:.6g} | {e['source']} | {'yes' if e['in_file'] else 'no'} |")
    for e in identified["not_identifiable"]:
        md.append(f"| {e['name']} | not identifiable | | {e['source']} | base value |")
    noise = ", ".join(f"{k} {v:.4g}" for k, v in identified["noise"].items())
    lat = identified["latency_s"]
    md += ["", f"Measured noise (the fits' residuals above quantisation): {noise}. Recorded "
           f"latency: p1 {lat['p1'] * 1e3:.3f}, median {lat['p50'] * 1e3:.3f}, p99 "
           f"{lat['p99'] * 1e3:.3f} ms.", "",
           f"![fit residuals]({rel('identify', 'residuals.png')})", "",
           f"Each fit's overlay: [excitation]({rel('identify', 'excitation.png')}), "
           f"[free swing]({rel('identify', 'free-swing.png')}).", "",
           "## The rig's distribution", "", "```yaml",
           (ctx.dir("distribution") / "rig-distribution.yaml").read_text().rstrip(), "```", "",
           "## Tuning", "",
           f"Space `{rec['tune']['outputs']['space']}`, {result['trials']} trials "
           f"({result['refused']} refused by the configuration) x {plan.draws} draws, seed "
           f"{plan.seed}. On the tuning draws: start " + ", ".join(
               f"{t} {100 * result['start_rates'][t]:.2f} %" for t in TIERS)
           + "; best " + ", ".join(f"{t} {100 * result['best_rates'][t]:.2f} %"
                                   for t in TIERS)
           + f" (trial {result['best_trial']}): " + ", ".join(
               f"{k} = {v:.6g}" for k, v in result["best_values"].items()) + ".", "",
           "## Verification on fresh draws", "",
           f"{verify_out['draws']} draws of the rig's distribution (seed {verify_out['seed']}), "
           "judged by the benchmark's tiers (each with its 95 % interval):", "",
           *[f"- {line}" for line in verify_out["rules"]], "", *_table(verify_out["tiers"]),
           "", (f"Tuned catch time: median {verify_out['catch_time_s']['median']:.2f} s, "
                f"p95 {verify_out['catch_time_s']['p95']:.2f} s."
                if verify_out["catch_time_s"] else "Tuned: no draw caught."), "",
           f"![expected catch time]({rel('verify', 'catch_time.png')})", "",
           f"![success by parameter]({rel('verify', 'success_by_parameter.png')})", "",
           "## Provenance", "", *[f"- {line}" for line in inputs], ""]
    (top / "report.md").write_text("\n".join(md))
    ctx.say(f"    wrote {top / 'report.md'} and {tuned}")
    return {"report": "../report.md", "tuned": "../tuned.yaml", "inputs": inputs}
