"""Commissioning: from a rig the controllers do not know to a configuration tuned for it,
in stages, each kept in a directory of its own so that a rerun resumes where the last
run stopped (docs/commissioning.md; the command is :mod:`pisc_robust.commission_cli`).

The stages, in order (:data:`STAGES`), each in ``DIR/N-stage``:

1. ``excitation``: the ``excitation`` scene run on the rig (``pisc_graph --scene
   excitation``), recorded;
2. ``free-swing``: the ``free-swing`` scene: on the rig the operator holds the pendulum
   at an angle and lets go; rehearsed, the simulated rig starts there (lockstep) or holds
   it until the run's first voltage lets go (the virtual rig);
3. ``identify``: both recordings through :mod:`pisc_robust.identify` (the motor, the
   friction and the command delay from the excitation; I and the pivot's friction from
   the free swing on top), merged into ``rig.yaml``, every estimate and interval in
   ``identified.json``, the sensors' noise and the latency as measured;
4. ``distribution``: the distribution of this rig (:mod:`pisc_robust.rig_distribution`);
5. ``tune``: :func:`pisc_robust.tune.tune` of ``rig.yaml`` on it (Optuna; its study is
   kept in the stage's directory and resumed), in the search space that follows the
   configuration (:func:`pisc_robust.tune_space.space_for`) unless one is named;
6. ``verify`` and 7. ``report``: fresh draws of the distribution, the report and the tuned
   file with its provenance (:mod:`pisc_robust.commission_report`).

A stage is done when its record (``stage.json``: the options it was made with, what it
made, when) is written, its last act. A rerun keeps every stage with a record and redoes
the first without one, from nothing (what an interrupted attempt left is removed), except
the tuning, whose study resumes with the trials it kept. A record made with other options
than the rerun's is refused, naming the differences: nothing is mixed.

How runs reach a rig (:class:`Rig`): ``driver`` (the rig on a serial port, or a virtual
rig's pseudo-terminal, with an operator at the terminal), ``lockstep`` (a plant parameter
file simulated in lockstep: a rehearsal) or ``virtual`` (a plant parameter file behind
``pisc_virtual_rig`` on the wall clock, through the driver: a rehearsal as on the rig).
"""

from __future__ import annotations

import datetime
import json
import math
import os
import shutil
import subprocess
import sys
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from pisc_robust.commission_report import digest_files
from pisc_msgs_py.config import ConfigError
from pisc_msgs_py.processes import stop_child

__all__ = ["RECORD", "STAGES", "CommissionError", "Context", "Plan", "Rig", "StageMismatch",
           "SwingUp", "commission", "digest_files", "draw_starts", "run_graph", "stage_dir",
           "swing_ups"]

STAGES = ("excitation", "free-swing", "identify", "distribution", "tune", "verify", "report")
RECORD = "stage.json"
KINDS = ("driver", "lockstep", "virtual")
#: How long a graph run may take beyond its own length (start-up, a loaded machine)
GRAPH_SLACK_S = 600.0


class CommissionError(RuntimeError):
    """A stage cannot be made; the message says why (and what to do)."""


class StageMismatch(CommissionError):
    """A stage kept in the directory was made with other options than this run's."""


@dataclass(frozen=True)
class Rig:
    """Where the runs go: ``driver`` (``port``), ``lockstep`` or ``virtual`` (``plant``,
    a parameter file of the plant). ``realtime``: SCHED_FIFO priority of the graph runs
    (0: none), and of the virtual rig ten above it."""

    kind: str
    port: str | None = None
    plant: str | None = None
    realtime: int = 0

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ConfigError(f"rig kind {self.kind!r}: one of {', '.join(KINDS)}")
        if ((self.kind == "driver") != (self.port is not None)
                or (self.kind == "driver") == (self.plant is not None)):
            raise ConfigError("--driver PORT and a rehearsal's --plant-config FILE exclude "
                              "each other, and one of them is needed")
        if self.kind != "driver" and not (self.plant and Path(self.plant).is_file()):
            raise ConfigError(f"--plant-config {self.plant}: no such file")
        if not 0 <= self.realtime <= 89:
            raise ConfigError(f"--realtime {self.realtime}: 0 (none) or 1-89")

    @property
    def operated(self) -> bool:
        """Whether a person at the terminal does what the rig needs (a real rig)."""
        return self.kind == "driver"

    def describe(self) -> str:
        return {"driver": f"the rig on {self.port}",
                "lockstep": f"a rehearsal in lockstep on the plant {self.plant}",
                "virtual": f"a rehearsal on the wall clock through pisc_virtual_rig with the "
                           f"plant {self.plant}"}[self.kind]

    def key(self) -> dict[str, Any]:
        if self.kind == "driver":
            return {"kind": "driver", "port": self.port}
        return {"kind": self.kind, "plant": str(self.plant),
                "plant_digest": digest_files([Path(self.plant)])[Path(self.plant).name]}


@dataclass(frozen=True)
class Plan:
    """What a commissioning does; every option is checked here, by its command-line name."""

    directory: Path
    rig: Rig
    config: str = "default"  # the configuration the controllers start from
    overrides: dict[str, Any] = field(default_factory=dict)  # --set: the rig as measured
    space: str | None = None  # None: the shipped space for the configuration
    widen: float = 3.0  # the identification's intervals, widened by this factor
    noise_span: float = 0.5  # each measured noise x (1 -+ this)
    mass_tolerance: float = 0.01  # relative, M and m as weighed
    length_tolerance: float = 0.02  # relative, l as measured
    start_x_m: float = 0.08  # the starts the rig will meet: x0 within +-this
    start_theta_rad: float = 0.05  # and theta within +-this of hanging
    trials: int = 40
    draws: int = 400
    verify_draws: int = 2000
    seed: int = 1
    sampler: str = "tpe"
    aim: str = "fast"  # pisc_tune's aim (tune.AIMS): the acceptance's "caught by 3 s"
    excitation_s: float = 60.0
    swing_s: float = 20.0
    prior: str = "thesis-rig"  # what the identification leaves unknown keeps this range
    workers: int | None = None
    scheduler: str | None = None

    def __post_init__(self) -> None:
        checks = [
            (self.widen >= 1.0, f"--widen {self.widen}: 1 or more (the factor the "
                                "identification's intervals are widened by)"),
            (0.0 <= self.noise_span < 1.0, f"--noise-span {self.noise_span}: in [0, 1)"),
            (0.0 <= self.mass_tolerance < 0.5, f"--mass-tolerance {self.mass_tolerance}: a "
                                               "fraction in [0, 0.5)"),
            (0.0 <= self.length_tolerance < 0.5, f"--length-tolerance "
                                                 f"{self.length_tolerance}: a fraction in "
                                                 "[0, 0.5)"),
            (self.start_x_m >= 0.0, f"--start-x {self.start_x_m}: 0 or more"),
            (self.start_theta_rad >= 0.0, f"--start-theta {self.start_theta_rad}: 0 or more"),
            (self.trials >= 1, f"--trials {self.trials}: at least 1"),
            (self.draws >= 1, f"--draws {self.draws}: at least 1"),
            (self.verify_draws >= 1, f"--verify-draws {self.verify_draws}: at least 1"),
            (self.seed >= 0, f"--seed {self.seed}: 0 or more"),
            (self.aim in ("safe", "fast"), f"--aim {self.aim}: safe or fast"),
            (self.excitation_s >= 5.0, f"--excitation-s {self.excitation_s}: at least 5"),
            (self.swing_s >= 3.0, f"--swing-s {self.swing_s}: at least 3"),
        ]
        for ok, message in checks:
            if not ok:
                raise ConfigError(message)
        for name in ("widen", "noise_span", "mass_tolerance", "length_tolerance",
                     "start_x_m", "start_theta_rad", "excitation_s", "swing_s"):
            if not math.isfinite(getattr(self, name)):
                raise ConfigError(f"{name}: {getattr(self, name)} is not finite")

    def stage_key(self, stage: str) -> dict[str, Any]:
        """The options stage ``stage`` depends on (its record must have the same)."""
        if stage in ("excitation", "free-swing"):
            length = self.excitation_s if stage == "excitation" else self.swing_s
            return {"rig": self.rig.key(), "config": self.config,
                    "overrides": _plain(self.overrides), "duration_s": length}
        if stage == "identify":
            return {"config": self.config, "overrides": _plain(self.overrides)}
        if stage == "distribution":
            return {k: getattr(self, k) for k in (
                "widen", "noise_span", "mass_tolerance", "length_tolerance", "start_x_m",
                "start_theta_rad", "prior")}
        if stage == "tune":
            return {k: getattr(self, k) for k in ("space", "trials", "draws", "seed",
                                                  "sampler", "aim")}
        if stage == "verify":
            return {"verify_draws": self.verify_draws, "seed": self.seed}
        return {}


Operator = Callable[[str], None]
Hook = Callable[[str, str], None]


@dataclass
class Context:
    """What every stage gets: the plan, the environment of the runs (ROS_DOMAIN_ID...),
    where to say what happens, the operator at a real rig, a hook for tests (called with
    (stage, event): 'start', 'trial', 'done'), and the records of the stages done."""

    plan: Plan
    env: dict[str, str]
    say: Callable[[str], None] = print
    operator: Operator | None = None
    hook: Hook | None = None
    records: dict[str, dict[str, Any]] = field(default_factory=dict)
    command: str = ""  # the command line of this run, for the provenance

    def dir(self, stage: str) -> Path:
        return stage_dir(self.plan.directory, stage)

    def event(self, stage: str, event: str) -> None:
        if self.hook is not None:
            self.hook(stage, event)

    def ask(self, text: str) -> None:
        """Tell the operator what to do and wait until they say it is done."""
        if self.operator is None:
            raise CommissionError("this stage needs an operator at the rig, and no one "
                                  "answers (standard input is not a terminal)")
        self.operator(text)


def stage_dir(directory: Path, stage: str) -> Path:
    return Path(directory) / f"{STAGES.index(stage) + 1}-{stage}"


def _plain(value: Any) -> Any:
    return json.loads(json.dumps(value, default=str))


def _now() -> str:
    return datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")


def _write_json(path: Path, data: Any) -> None:
    """Written whole or not at all (a record is a stage's last act)."""
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(data, indent=1, default=str) + "\n")
    os.replace(tmp, path)


def commission(plan: Plan, env: Mapping[str, str] | None = None,
               say: Callable[[str], None] = print, operator: Operator | None = None,
               hook: Hook | None = None, command: str = "") -> dict[str, dict[str, Any]]:
    """Make every stage not made yet; the records of all. Raises :class:`ConfigError` on
    bad input, :class:`CommissionError` when a stage cannot be made (and
    :class:`KeyboardInterrupt` as it came): what is done stays done. ``command`` (the
    command line) goes into ``DIR/commands.log`` with the time, for the provenance."""
    from pisc_robust import commission_report as report

    functions = {"excitation": _excitation, "free-swing": _free_swing,
                 "identify": _identify, "distribution": _distribution, "tune": _tune,
                 "verify": report.verify, "report": report.report}
    ctx = Context(plan, dict(os.environ if env is None else env), say, operator, hook,
                  command=command)
    plan.directory.mkdir(parents=True, exist_ok=True)
    with (plan.directory / "commands.log").open("a") as log:
        log.write(f"{_now()} {command or '(library call)'}\n")
    say(f"commissioning {plan.rig.describe()} in {plan.directory}")
    for n, stage in enumerate(STAGES, 1):
        where = ctx.dir(stage)
        key = _plain(plan.stage_key(stage))
        record_path = where / RECORD
        head = f"[{n}/{len(STAGES)}] {stage}"
        if record_path.is_file():
            record = json.loads(record_path.read_text())
            diff = [f"{k} {record['key'].get(k)!r} (now {v!r})" for k, v in key.items()
                    if record["key"].get(k) != v]
            if diff:
                raise StageMismatch(
                    f"{where} was made with another " + "; ".join(diff) + f". Remove {where}"
                    " and the stages after it to make them again, or use another directory")
            say(f"{head}: done earlier ({record['made']}), kept")
            ctx.records[stage] = record
            continue
        if where.exists() and stage != "tune":  # what an interrupted attempt left
            shutil.rmtree(where)
        where.mkdir(parents=True, exist_ok=True)
        say(f"{head}: ...")
        ctx.event(stage, "start")
        outputs = functions[stage](ctx, where)
        ctx.event(stage, "done")
        record = {"stage": stage, "key": key,
                  "made": _now(),
                  "outputs": _plain(outputs)}
        _write_json(record_path, record)
        ctx.records[stage] = record
    return ctx.records


# -- runs on the rig -------------------------------------------------------------------


@dataclass(frozen=True)
class GraphRun:
    command: list[str]
    returncode: int
    stdout: str
    stderr: str

    def line(self, start: str) -> str:
        return next((x for x in self.stdout.splitlines() if x.startswith(start)), "")


def run_graph(rig: Rig, args: list[str], env: Mapping[str, str], duration_s: float,
              rig_args: list[str] = ()) -> GraphRun:
    """``pisc_graph ARGS`` on ``rig``: with ``--plant-config`` in lockstep, ``--driver``
    on a port, or through a ``pisc_virtual_rig`` started for the run (``rig_args``: its
    own options, e.g. the start). The run's output and exit status; :class:`CommissionError`
    when the graph could not run (exit 2, or no end)."""
    from pisc_plant.rig_process import RigProcess

    command = [sys.executable, "-m", "pisc_bringup.graph_cli", *args]
    if rig.realtime and rig.kind != "lockstep":
        command += ["--realtime", str(rig.realtime)]
    virtual = None
    if rig.kind == "lockstep":
        command += ["--plant-config", str(rig.plant)]
    elif rig.kind == "driver":
        command += ["--driver", str(rig.port)]
    else:
        extra = ["--realtime", str(rig.realtime + 10)] if rig.realtime else []
        try:
            virtual = RigProcess([*extra, "--params-file", str(rig.plant), *rig_args],
                                 env=dict(env))
        except (RuntimeError, TimeoutError) as exc:
            raise CommissionError(f"the virtual rig did not start: {exc}") from None
        command += ["--driver", virtual.device]
    child = subprocess.Popen(command, env=dict(env), stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True)
    try:
        stdout, stderr = child.communicate(timeout=duration_s + GRAPH_SLACK_S)
    except subprocess.TimeoutExpired:
        stop_child(child)
        raise CommissionError(f"{' '.join(command[2:])}: no end after "
                              f"{duration_s + GRAPH_SLACK_S:.0f} s") from None
    except BaseException:  # Ctrl-C: the graph stops as it does on SIGINT (0 V first)
        stop_child(child)
        raise
    finally:
        if virtual is not None:
            virtual.stop()
    run = GraphRun(command, child.returncode, stdout, stderr)
    if child.returncode not in (0, 1):
        raise CommissionError(f"{' '.join(command[2:])} did not run (exit "
                              f"{child.returncode}): {stderr.strip()[-1500:]}")
    return run


def _experiment(ctx: Context, where: Path, scene: str, duration: float,
                rig_args: list[str] = ()) -> dict[str, Any]:
    bag = where / "bag"
    sets = [a for k, v in ctx.plan.overrides.items() for a in ("--set", f"{k}={v}")]
    run = run_graph(ctx.plan.rig, ["--scene", scene, "--duration", f"{duration:g}",
                                   "--bag", str(bag), *sets], ctx.env, duration, rig_args)
    said = run.line("experiment ")
    if run.returncode != 0:
        raise CommissionError(f"the {scene} run faulted: {said or run.stdout[-800:]} (the "
                              f"bag: {bag})")
    ctx.say(f"    {said}")
    files = sorted(bag.glob("*.mcap"))
    return {"bag": "bag", "bag_files": digest_files(files), "said": said,
            "command": [Path(run.command[0]).name, *run.command[1:]]}


def _excitation(ctx: Context, where: Path) -> dict[str, Any]:
    plan = ctx.plan
    if plan.rig.operated:
        ctx.ask(f"Excitation ({plan.excitation_s:g} s): put the cart near the middle of the "
                "track, the pendulum hanging still, and keep clear of the track: the cart "
                "will shake back and forth. Press Enter to start.")
    return _experiment(ctx, where, "excitation", plan.excitation_s)


def _free_swing(ctx: Context, where: Path) -> dict[str, Any]:
    from pisc_sim.scene import load_scene

    plan = ctx.plan
    angle = float(load_scene("free-swing").overrides["initial.theta_rad"])
    off = abs(math.pi - angle)
    if plan.rig.operated:
        ctx.ask(f"Free swing ({plan.swing_s:g} s): hold the pendulum still about {off:.1f} "
                f"rad ({math.degrees(off):.0f} degrees) off hanging, the cart near the "
                "middle. Press Enter, then let go as soon as the run starts (a few seconds); "
                "the cart is held where it is.")
    # rehearsed: the plant starts at the scene's angle; the virtual rig holds it there
    # until the run's first voltage lets go, as a hand would
    rig_args = ["--set", f"initial.theta_rad={angle!r}", "--hold"]
    return _experiment(ctx, where, "free-swing", plan.swing_s, rig_args)


# -- identification -------------------------------------------------------------------


def _identify(ctx: Context, where: Path) -> dict[str, Any]:
    from pisc_robust.identify import identify
    from pisc_robust.identify_data import DEFAULT_FIT, IdentifyError, parse_fit, read_recording
    from pisc_robust.identify_report import format_report, load_base, plot_overlay, write_result
    from pisc_robust import rig_distribution as rd
    from pisc_sim.configuration import load_graph_config, params_file_text

    plan = ctx.plan
    _, flat = load_graph_config(plan.config, plan.overrides)
    base = where / "base.yaml"  # the configuration with the rig as measured (--set)
    base.write_text(f"# {plan.config} with " + (", ".join(
        f"{k} = {v}" for k, v in plan.overrides.items()) or "no change") + "\n"
        + params_file_text(flat))
    results = {}
    for stage, start in (("excitation", base), ("free-swing", where / "excitation.yaml")):
        bag = ctx.dir(stage) / "bag"
        try:
            recording = read_recording(bag)
            model, base_flat, _ = load_base(str(start), [recording])
            keys = list(DEFAULT_FIT.get(recording.experiment, DEFAULT_FIT["none"]))
            if stage == "excitation":
                keys.append("delay")  # the latency's unrecorded part, on any clock
            ctx.say(f"    {stage}: fitting {', '.join(keys)}")
            result = identify([recording], parse_fit(keys), model,
                              progress=lambda text: ctx.say(f"      {text}"))
        except IdentifyError as exc:  # (FitError included)
            raise CommissionError(f"identification of the {stage} run failed: {exc}") from None
        if not result.estimates:
            raise CommissionError(f"the {stage} run identified nothing:\n"
                                  + format_report(result))
        ctx.say("\n".join(f"      {line}" for line in format_report(result).splitlines()))
        write_result(result, base_flat, str(start), where / f"{stage}.yaml",
                     f"pisc_commission ({stage} of {plan.directory})")
        plot_overlay(result, where / f"{stage}.png")
        results[stage] = result
    from pisc_robust.commission_report import plot_residuals

    plot_residuals(results, where / "residuals.png")
    identified = rd.merge(results, load_graph_config(str(where / "free-swing.yaml"))[1])
    (where / "rig.yaml").write_text(rd.rig_file_text(identified))
    _write_json(where / "identified.json", identified)
    for line in rd.describe(identified):
        ctx.say(f"    {line}")
    return {"rig": "rig.yaml", "identified": "identified.json",
            "plots": ["residuals.png", "excitation.png", "free-swing.png"]}


def _distribution(ctx: Context, where: Path) -> dict[str, Any]:
    from pisc_robust import rig_distribution as rd
    from pisc_robust.uncertainty import load_distribution
    from pisc_sim.configuration import load_graph_config

    identify = ctx.dir("identify")
    identified = json.loads((identify / "identified.json").read_text())
    rig_file = identify / "rig.yaml"
    config, _ = load_graph_config(str(rig_file))
    prior = load_distribution(ctx.plan.prior, config)
    try:
        text = rd.distribution_text(identified, ctx.plan, prior)
    except ValueError as exc:
        raise CommissionError(f"{where.name}: {exc}") from None
    path = where / "rig-distribution.yaml"
    path.write_text(text)
    distribution = load_distribution(str(path), config)  # it reads as any distribution
    from pisc_robust.robustness_report import describe_distribution

    ctx.say("\n".join(f"    {line}" for line in describe_distribution(distribution)
                      .splitlines()))
    return {"distribution": path.name, "digest": distribution.digest}


# -- tuning ----------------------------------------------------------------------------


def _tune(ctx: Context, where: Path) -> dict[str, Any]:
    from pisc_robust.cluster import chunk_runner, workers_for
    from pisc_robust.robustness import CHUNK_DRAWS
    from pisc_runs.verdict import Criteria
    from pisc_robust.tune import Tuning, trials_kept, tune, tuned_file_text
    from pisc_robust.tune_space import load_space, space_for
    from pisc_robust.uncertainty import load_distribution
    from pisc_sim.configuration import load_graph_config

    plan = ctx.plan
    rig_file = str(ctx.dir("identify") / "rig.yaml")
    config, flat = load_graph_config(rig_file)
    distribution = load_distribution(
        str(ctx.dir("distribution") / "rig-distribution.yaml"), config)
    space_name = plan.space or space_for(flat)
    space = load_space(space_name, flat)
    tuning = Tuning(rig_file, {}, distribution, space, plan.draws, plan.seed, plan.sampler,
                    Criteria(), aim=plan.aim)
    storage = f"sqlite:///{where / 'study.db'}"
    kept = trials_kept(tuning, storage)
    ctx.say(f"    space {space.name} ({len(space.dimensions)} parameters"
            f"{'' if plan.space else ', the one for this configuration'}); {plan.trials} "
            f"trials x {plan.draws} draws, seed {plan.seed}, aim {plan.aim}"
            + (f"; resuming the study's {kept} trials" if kept else ""))
    chunks = -(-plan.draws // CHUNK_DRAWS)
    workers = workers_for(chunks, plan.workers, plan.scheduler)

    def progress(done: int, best: dict[str, float]) -> None:
        ctx.say(f"      trial {done}/{plan.trials}: best " + ", ".join(
            f"{t} {100 * best.get(t, 0.0):.1f} %" for t in ("safe", "caught", "fast")))
        ctx.event("tune", "trial")

    with chunk_runner(workers, plan.scheduler) as map_chunks:
        result = tune(tuning, plan.trials, storage, map_chunks, progress)
    tiers = ("safe", "caught", "fast")  # (the rates also hold the hold's RMS, in A)
    ctx.say("    start on the tuning draws: " + ", ".join(
        f"{t} {100 * result.start_rates[t]:.2f} %" for t in tiers)
        + "; best: " + ", ".join(f"{t} {100 * result.best_rates[t]:.2f} %" for t in tiers)
        + f" (trial {result.best_trial})")
    date = datetime.date.today().isoformat()
    (where / "tuned.yaml").write_text(tuned_file_text(
        result, tuning, f"pisc_commission (tune of {plan.directory})", date, storage))
    kept = {k: v for k, v in asdict(result).items() if k != "best_flat"}
    return {"tuned": "tuned.yaml", "storage": "study.db", "space": plan.space or space.name,
            "space_digest": space.digest, "distribution_digest": distribution.digest,
            "result": kept, "study_name": tuning.study_name}


# -- swing-ups through the graph ------------------------------------------------------


@dataclass(frozen=True)
class SwingUp:
    x0_m: float
    theta0_rad: float
    passed: bool  # the tier's verdict (the graph's exit status)
    safe: bool
    verdict: str  # the summary's line of the tier
    bag: str


def draw_starts(n: int, seed: int, start_x_m: float, start_theta_rad: float,
                nominal: tuple[float, float] = (0.0, math.pi)) -> list[tuple[float, float]]:
    """``n`` starts uniform over the ranges the rig's distribution gives them (cart at
    ``nominal[0]`` +- ``start_x_m``, the pendulum within ``start_theta_rad`` of
    hanging, at rest), from ``seed``."""
    import numpy as np

    u = np.random.default_rng([seed, 0x5714]).random((n, 2)) * 2.0 - 1.0
    return [(float(nominal[0] + start_x_m * a), float(nominal[1] + start_theta_rad * b))
            for a, b in u]


def swing_ups(rig: Rig, config: str, starts: list[tuple[float, float]], bags: Path,
              env: Mapping[str, str], tier: str = "fast", duration_s: float = 12.0,
              say: Callable[[str], None] = print) -> list[SwingUp]:
    """One swing-up through the graph with ``config`` from each start, judged by the
    benchmark's ``tier`` (the graph's ``--tier``). Lockstep: the plant starts there; the
    virtual rig holds the start until the run's first voltage (``--hold``); a real rig
    starts where the operator left it."""
    out = []
    for k, (x0, th0) in enumerate(starts):
        bag = bags / f"swing-up-{k:02d}"
        start = ["--set", f"initial.x_m={x0!r}", "--set", f"initial.theta_rad={th0!r}"]
        args = ["--config", config, "--duration", f"{duration_s:g}", "--tier", tier,
                "--bag", str(bag)]
        if rig.kind == "lockstep":
            args += start
        run = run_graph(rig, args, env, duration_s, [*start, "--hold"])
        verdict = run.line(f"{tier:<23}")
        safe = run.line("safe ").split()[1:2] == ["yes:"]
        out.append(SwingUp(x0, th0, run.returncode == 0, safe, verdict, str(bag)))
        say(f"    x0 {x0:+.3f} m, theta0 {th0:.3f} rad: {verdict}")
    return out
