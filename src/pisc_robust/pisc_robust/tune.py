"""Search the controllers' parameters for the highest success rate over a distribution,
over a search space (:mod:`pisc_robust.tune_space`).

:func:`tune` runs an Optuna study (TPE by default, or CMA-ES, seeded): every trial scores
a candidate by :func:`pisc_robust.robustness.evaluate` over the **same** draws (the
study's seed: common random numbers), so trials compare fairly and the same seed gives
the same result. A candidate that the configuration refuses (:class:`ConfigError`, e.g.
the gain condition (3.29)) scores 0 and is marked ``refused`` in its user attributes.
When the start configuration lies inside the space it is the first trial.

A study lives in an Optuna storage (an SQLite file by default) and can be resumed by the
same command; the storage holds one tuning: its distribution's digest, configuration,
draws, seed, space, criteria and sampler are recorded in the study's name and user
attributes, and a storage that holds another tuning is refused (:class:`StudyMismatch`),
never mixed in.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from pisc_sim.configuration import load_graph_config
from pisc_robust.robustness import MapChunks, evaluate, prepare
from pisc_robust.tune_space import Space, full_flat
from pisc_runs.verdict import TIERS, Criteria
from pisc_robust.uncertainty import Distribution
from pisc_control.supervisor import Supervisor
from pisc_msgs_py.config import ConfigError

__all__ = ["AIMS", "SAMPLERS", "StudyMismatch", "TuneResult", "Tuning", "open_study",
           "provenance", "score_for", "trials_kept", "tune", "tuned_file_text"]

SAMPLERS = ("tpe", "cmaes")
#: What a trial's score puts first: ``safe`` (:meth:`Outcomes.score`: one more safe draw
#: outweighs any number of catches) or ``fast`` (one more draw of the fast tier, caught for
#: good by 3 s and held, and so safe, outweighs any number of safe ones: a candidate that
#: never swings up is safe on every draw, and wins ``safe``'s order wherever the start
#: leaves the safe range on a few)
AIMS = ("safe", "fast")


class StudyMismatch(ConfigError):
    """The storage holds a study of another tuning (distribution, draws, seed, space...)."""


@dataclass(frozen=True)
class Tuning:
    """What a study is about; everything in :meth:`key` must match to resume it."""

    config: str  # a configuration name or parameter file
    overrides: dict[str, Any]  # --set
    distribution: Distribution
    space: Space
    draws: int
    seed: int
    sampler: str = "tpe"
    criteria: Criteria = Criteria()
    #: starts at rest from hanging, evenly over x0 in [-0.1, 0.1] m, on the configuration's
    #: own plant, that must all be fast (caught and held by the fast tier's rule); 0: none
    nominal_starts: int = 0
    #: and their set-point RMS in the fast tier's hold window at most this (a hold that
    #: chatters); 0: no limit
    hold_rms_a: float = 0.0
    aim: str = "safe"  # AIMS: what a trial's score puts first

    def __post_init__(self) -> None:
        if self.sampler not in SAMPLERS:
            raise ConfigError(f"sampler {self.sampler!r}: one of {', '.join(SAMPLERS)}")
        if self.aim not in AIMS:
            raise ConfigError(f"aim {self.aim!r}: one of {', '.join(AIMS)}")
        if self.draws < 1:
            raise ConfigError(f"draws = {self.draws}: at least one draw")
        if not (math.isfinite(self.hold_rms_a) and self.hold_rms_a >= 0.0):
            raise ConfigError(f"hold RMS limit {self.hold_rms_a} A: 0 (none) or positive")
        if self.hold_rms_a and not self.nominal_starts:
            raise ConfigError("a hold RMS limit applies to the nominal starts: give some")
        if self.nominal_starts < 0:
            raise ConfigError(f"nominal starts {self.nominal_starts}: 0 (none) or more")

    def key(self) -> dict[str, Any]:
        from pisc_sim.configuration import config_path

        text = config_path(self.config).read_text()
        return {
            "config": self.config,
            "config_digest": hashlib.sha256(text.encode()).hexdigest()[:16],
            "overrides": yaml.safe_dump(self.overrides, sort_keys=True).strip(),
            "distribution": self.distribution.name,
            "distribution_digest": self.distribution.digest,
            "draws": self.draws,
            "seed": self.seed,
            "space": self.space.name,
            "space_digest": self.space.digest,
            "criteria": yaml.safe_dump(asdict(self.criteria), sort_keys=True).strip(),
            "nominal_starts": self.nominal_starts,
            "hold_rms_a": self.hold_rms_a,
            "sampler": self.sampler,
            **({} if self.aim == "safe" else {"aim": self.aim}),
        }

    @property
    def study_name(self) -> str:
        k = self.key()
        return (f"pisc_tune {Path(self.config).stem} {k['distribution']} "
                f"{k['distribution_digest']} draws {self.draws} seed {self.seed} space "
                f"{k['space_digest']} {self.sampler}")


@dataclass(frozen=True)
class TuneResult:
    start_score: float  # Outcomes.score: safe first, then caught, then fast
    best_score: float
    start_rates: dict[str, float]  # each tier's fraction of the draws
    best_rates: dict[str, float]
    best_trial: int
    best_values: dict[str, float]  # by dimension name
    best_flat: dict[str, Any]  # the whole configuration with the best values
    trials: int  # complete trials in the study
    refused: int  # of which the configuration refused


def _sampler(tuning: Tuning, offset: int) -> Any:
    import optuna

    seed = tuning.seed + offset
    if tuning.sampler == "cmaes":
        # from the middle of the space (the start, when inside, is the first trial anyway)
        return optuna.samplers.CmaEsSampler(seed=seed)
    # trials run one after another: no constant liar (a trial that a killed run left
    # RUNNING would otherwise count as a bad value for ever)
    return optuna.samplers.TPESampler(seed=seed, multivariate=True, constant_liar=False)


def open_study(tuning: Tuning, storage: str) -> Any:
    """Create or resume the study of ``tuning`` in ``storage``; :class:`StudyMismatch`
    if the storage holds another tuning."""
    import optuna

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    from sqlalchemy.exc import SQLAlchemyError

    key = tuning.key()
    try:
        summaries = optuna.get_all_study_summaries(storage, include_best_trial=False)
    except (SQLAlchemyError, ValueError, ImportError) as exc:
        raise ConfigError(f"{storage}: cannot open the study storage "
                          f"({str(exc).splitlines()[0]})") from None
    existing = 0
    for summary in summaries:
        theirs = summary.user_attrs.get("pisc_tune")
        if summary.study_name == tuning.study_name and theirs in (key, None):
            existing = summary.n_trials
            continue
        if not isinstance(theirs, Mapping):
            raise StudyMismatch(f"{storage}: holds study '{summary.study_name}', which is not "
                                "a pisc_tune study; use another --out or --storage")
        diff = [f"{k} {theirs.get(k)!r} (now {v!r})" for k, v in key.items()
                if theirs.get(k) != v]
        raise StudyMismatch(f"{storage}: holds a tuning with another "
                            + "; ".join(diff or [f"study name '{summary.study_name}'"])
                            + ". Resuming mixes no other tuning in: use another --out or "
                            "--storage, or delete the study file to start again")
    # a resumed study samples on from another seed than the first run's start
    study = optuna.create_study(storage=storage, study_name=tuning.study_name,
                                direction="maximize", load_if_exists=True,
                                sampler=_sampler(tuning, existing))
    if "pisc_tune" not in study.user_attrs:
        study.set_user_attr("pisc_tune", key)
    return study


def score_for(aim: str, outcomes: Any, penalty: float = 0.0) -> float:
    """A trial's score by ``aim`` (:data:`AIMS`), at most 1; ``penalty`` (in draws) is
    taken off the catches (``safe``: :meth:`Outcomes.score`, safe first up to
    :data:`SAFE_TARGET`) or off the fast draws (``fast``)."""
    if aim == "safe":
        return outcomes.score(penalty, SAFE_TARGET)
    n = len(outcomes)
    fast, safe = (int(np.sum(outcomes.passed(t))) for t in ("fast", "safe"))
    return ((fast - penalty) * (n + 1.0) + safe) / (n * (n + 2.0))


def trials_kept(tuning: Tuning, storage: str) -> int:
    """The complete trials of ``tuning``'s study in ``storage`` (0 if it has none)."""
    import optuna
    from optuna.trial import TrialState

    try:
        study = optuna.load_study(study_name=tuning.study_name, storage=storage)
    except KeyError:
        return 0
    return len(study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,)))


class _NoInterruptTraceback:
    """A logging filter for Optuna's two warnings about a trial that an exception ended
    (its traceback, then its value None): the exception goes on to the caller (no trial
    error is caught), which reports it, Ctrl-C in a line rather than a traceback."""

    @staticmethod
    def filter(record: Any) -> bool:
        info = record.exc_info
        if info and isinstance(info[1], KeyboardInterrupt):
            return False
        return not str(record.msg).endswith("failed with value None.")


def tune(tuning: Tuning, trials: int, storage: str, map_chunks: MapChunks | None = None,
         progress: Callable[[int, dict[str, float]], None] | None = None) -> TuneResult:
    """Run the study of ``tuning`` until it holds ``trials`` complete trials.

    ``progress(done, rates)`` is called after each trial with the number of complete
    trials and the tiers' rates of the best trial so far (:meth:`Outcomes.score`).
    """
    start_config, start_flat = load_graph_config(tuning.config, tuning.overrides)
    draws = tuning.distribution.draw(tuning.draws, tuning.seed)
    _, plant = prepare(start_config, tuning.distribution)
    start_values = tuning.space.values(full_flat(start_flat))
    inside = tuning.space.contains(start_values)
    study = open_study(tuning, storage)

    def score(values: Mapping[str, float]) -> tuple[float, dict[str, float], str]:
        overrides = {**tuning.overrides, **tuning.space.overrides(start_flat, values)}
        try:
            config, _ = load_graph_config(tuning.config, overrides)
            Supervisor(config.supervisor)  # the gain condition and the catch design
        except ConfigError as exc:
            return 0.0, dict.fromkeys(TIERS, 0.0), str(exc)
        nominal = nominal_fast(config, tuning.criteria, tuning.nominal_starts,
                               tuning.hold_rms_a)
        config, _ = prepare(config, tuning.distribution)
        outcomes = evaluate(config, plant, draws, tuning.criteria, tuning.seed, map_chunks)
        rms = outcomes.hold_setpoint_rms_a[outcomes.caught]
        rates = outcomes.rates()
        rates["hold_rms_a"] = float(np.median(rms)) if rms.size else -1.0
        # the nominal rig's starts cost catches: caught late (or chattering) from every
        # start, as much as half the draws caught late
        penalty = 0.0
        if nominal is not None:
            rates["nominal_fast"] = nominal
            penalty += 0.5 * len(outcomes) * (1.0 - nominal)
        return score_for(tuning.aim, outcomes, penalty), rates, ""

    def objective(trial: Any) -> float:
        values = {d.name: trial.suggest_float(d.name, d.low, d.high, log=d.log)
                  for d in tuning.space.dimensions}
        value, rates, refused = score(values)
        trial.set_user_attr("rates", rates)
        if refused:
            trial.set_user_attr("refused", refused)
        return value

    from optuna.trial import TrialState

    def complete() -> list[Any]:
        return study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,))

    if inside and not study.get_trials(deepcopy=False):
        study.enqueue_trial(start_values, user_attrs={"start": True})

    def callback(study_: Any, trial: Any) -> None:
        if progress is not None:
            progress(len(complete()), study_.best_trial.user_attrs.get("rates", {}))

    remaining = trials - len(complete())
    if remaining > 0:
        import logging

        quiet = logging.getLogger("optuna.study._optimize")
        quiet.addFilter(_NoInterruptTraceback)
        try:
            study.optimize(objective, n_trials=remaining, callbacks=[callback], catch=())
        finally:
            quiet.removeFilter(_NoInterruptTraceback)
    done = complete()
    accepted = [t for t in done if "refused" not in t.user_attrs]
    if not accepted:
        refusal = done[-1].user_attrs["refused"] if done else "no trial completed"
        raise ConfigError(f"the configuration refused all {len(done)} candidates, the last "
                          f"with: {refusal}; check the search space")
    best = max(accepted, key=lambda t: t.value)  # the first of equals
    start = next((t for t in done if t.user_attrs.get("start")), None)
    if start is None and "start_score" not in study.user_attrs:
        # outside the space (or its trial was killed): scored once, kept with the study
        value, rates, _ = score(start_values)
        study.set_user_attr("start_score", value)
        study.set_user_attr("start_rates", rates)
    if start is not None:
        start_score, start_rates = float(start.value), start.user_attrs["rates"]
    else:
        start_score = float(study.user_attrs["start_score"])
        start_rates = study.user_attrs["start_rates"]
    best_values = {d.name: float(best.params[d.name]) for d in tuning.space.dimensions}
    best_flat = full_flat({**start_flat,
                           **tuning.space.overrides(start_flat, best_values)})
    return TuneResult(start_score, float(best.value), dict(start_rates),
                      dict(best.user_attrs["rates"]), best.number, best_values, best_flat,
                      len(done), sum(1 for t in done if "refused" in t.user_attrs))


#: safe draws count first up to this fraction (the benchmark's target); beyond it a more
#: or less rare unsafe draw, which a few hundred draws cannot tell apart, does not decide
SAFE_TARGET = 0.999


def nominal_fast(config: Any, criteria: Criteria, starts: int, rms_limit_a: float = 0.0
                 ) -> float | None:
    """The fraction of ``starts`` starts at rest from the configuration's initial angle,
    x0 evenly in [-0.1, 0.1] m, on its own plant, that the fast tier passes with a hold's
    set-point RMS of at most ``rms_limit_a`` (0: any) (None for no starts)."""
    if starts == 0:
        return None
    from pisc_sim.closed_loop import simulate_batch

    x0 = np.linspace(-0.1, 0.1, starts) if starts > 1 else np.zeros(1)
    hold = criteria.fast_hold_from_s
    out = simulate_batch(config, x0, criteria.run_s, hold, hold_box=(criteria.theta_rad,
                                                                    criteria.x_m))
    safety = config.supervisor.safety
    safe = ~out.faulted & (out.x_min_m >= safety.x_min_m) & (out.x_max_m <= safety.x_max_m)
    fast = safe & (out.caught_at_s <= criteria.fast_by_s) & (out.unheld_at_s < hold)
    if rms_limit_a > 0.0:
        fast &= out.hold_setpoint_rms_a <= rms_limit_a
    return float(np.mean(fast))


def provenance(result: TuneResult, tuning: Tuning, command: str, date: str,
               storage: str) -> list[str]:
    """The lines that say where a tuned file comes from."""
    key = tuning.key()
    overrides = " ".join(f"--set {k}={v}" for k, v in tuning.overrides.items())
    return [
        f"command: {command}",
        f"date: {date}",
        f"configuration: {tuning.config} (digest {key['config_digest']})"
        + (f" {overrides}" if overrides else ""),
        f"distribution: {tuning.distribution.name} (digest {tuning.distribution.digest})",
        f"space: {tuning.space.name} (digest {tuning.space.digest}): "
        + ", ".join(d.name for d in tuning.space.dimensions),
        f"draws {tuning.draws}, seed {tuning.seed}, sampler {tuning.sampler}"
        f"{', aim fast' if tuning.aim == 'fast' else ''}, trials "
        f"{result.trials} ({result.refused} refused by the configuration), study in {storage}",
        f"constraints: {tuning.nominal_starts} nominal starts fast"
        + (f", their hold's set-point RMS at most {tuning.hold_rms_a:g} A"
           if tuning.hold_rms_a else "") if tuning.nominal_starts else "constraints: none",
        f"tiers on the same draws: start {_rates(result.start_rates)}; best "
        f"{_rates(result.best_rates)} (trial {result.best_trial})",
        "best: " + ", ".join(f"{k} = {v:.6g}" for k, v in result.best_values.items()),
    ]


def tuned_file_text(result: TuneResult, tuning: Tuning, command: str, date: str,
                    storage: str) -> str:
    """A ROS 2 parameter file of the whole configuration with the best values, headed by
    comment lines that record its provenance."""
    from pisc_sim.configuration import params_file_text

    head = ["pisc_tune: the configuration with the best values the search found"]
    head += provenance(result, tuning, command, date, storage)
    return "".join(f"# {line}\n" for line in head) + params_file_text(
        {k: _plain(v) for k, v in result.best_flat.items()})


def _rates(rates: Mapping[str, float]) -> str:
    text = ", ".join(f"{tier} {100 * rates[tier]:.2f} %" for tier in TIERS)
    if rates.get("hold_rms_a", -1.0) >= 0.0:
        text += f", hold's median set-point RMS {rates['hold_rms_a']:.4f} A"
    if "nominal_fast" in rates:
        text += f", nominal starts fast {100 * rates['nominal_fast']:.1f} %"
    return text


def _plain(value: Any) -> Any:
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value
