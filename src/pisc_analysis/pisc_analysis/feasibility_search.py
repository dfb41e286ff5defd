"""The search for a witness: a voltage sequence that swings a rig up and holds it.

:func:`find_witness` runs three searches, all on the compiled plant
(:class:`pisc_plant.plant.Plant`), for the problem of :mod:`pisc_analysis.feasibility`:

1. **Perfect-knowledge feedback** (:func:`pisc_analysis.feasibility_feedback.feedback_search`):
   an energy pump on the true pendulum energy with a track guard, the force computed
   from the true model (3.3), (3.5), handed to a discrete LQR hold in the catch region;
   many random gain sets at once, as a batch of rigs.
2. **Direct shooting** (:func:`pisc_analysis.feasibility_shooting.shoot`): the voltage
   piecewise constant over knots, ``scipy.optimize.least_squares`` on the terminal state
   (upright at rest) with the track and current limits as penalty residuals, started
   from the best feedback rollouts and from random pumps; the LQR hold takes over at the
   end of the horizon.
3. **Multiple shooting** (:func:`pisc_analysis.feasibility_shooting.transcribe`,
   optional): the catch deadline brought down by continuation from the best feedback
   rollouts, 5 ms knots, 0.2 s segments.

Every candidate is re-simulated from scratch as one voltage sequence and checked
(:func:`pisc_analysis.feasibility.verify`); only a sequence that passes is a witness. A
witness proves that the rig can be swung up and held: the draw is *feasible*. A search
that fails proves nothing; :func:`pisc_analysis.feasibility_bound.energy_bound` gives
necessary conditions that do (an energy budget and the comparison lemma's climb time to
the catch region's energy), and :class:`Search` says which applies.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from pisc_analysis.feasibility import (THETA, THETA_DOT, Limits, Rig, Verdict, rollout,
                                       samples, verify, wrap)
from pisc_analysis.feasibility_bound import EnergyBound, energy_bound
from pisc_analysis.feasibility_feedback import feedback_search, hold_from, hold_gain
from pisc_analysis.feasibility_shooting import Transcription, expand, shoot, transcribe

__all__ = ["Search", "find_witness"]


@dataclass(frozen=True)
class Search:
    """What :func:`find_witness` found for one rig."""

    feasible: bool
    how: str  # 'feedback', 'shooting', 'multiple shooting',
    # 'bound' (proved infeasible) or 'not found'
    voltages: np.ndarray | None  # the witness, one value a period (None without one)
    verdict: Verdict | None  # the witness's check, or the best failed candidate's
    bound: EnergyBound
    tried: int  # candidates checked
    # the earliest catch deadline multiple shooting met (its residual zero), inf if none;
    # NaN when it did not run
    transcribed_s: float = math.nan


def find_witness(rig: Rig, limits: Limits, rng: np.random.Generator, rollouts: int = 48,
                 rounds: int = 4, restarts: int = 2, knot_periods: int = 8,
                 max_nfev: int = 30, transcription: Transcription | None = None) -> Search:
    """Search for a witness, stopping at the first.

    The energy bound first (:func:`energy_bound`). Then ``rounds`` batches of
    ``rollouts`` perfect-knowledge feedback gain sets (:func:`feedback_search`). If none
    passes, direct shooting (:func:`shoot`) from the ``restarts`` best rollouts, horizon
    at their closest approach to upright before ``catch_by_s`` (knots of
    ``knot_periods`` periods), each handed to the LQR hold. With ``transcription``,
    last, multiple shooting with the catch deadline brought down by continuation
    (:func:`transcribe`) from the best rollouts. A candidate counts only once
    :func:`verify` passes it, re-simulated alone.
    """
    bound = energy_bound(rig, limits)
    if bound.infeasible:
        return Search(False, "bound", None, None, bound, 0)
    period = rig.period_s
    steps = int(round(limits.duration_s / period))
    k_gain = hold_gain(rig)
    found, verdict, pool, tried = feedback_search(rig, limits, rng, rollouts, rounds, k_gain)
    if found is not None:
        return Search(True, "feedback", found, verdict, bound, tried)
    volts, states, badness = pool.voltages, pool.states, pool.badness
    best = verify(rig, limits, volts[int(np.argmin(badness))])
    tried += 1
    last = samples(limits.catch_by_s, period)
    region = wrap(states[:, : last + 1, THETA]) ** 2 + limits.k_va * states[:, : last + 1,
                                                                            THETA_DOT] ** 2
    for j in np.argsort(badness)[:restarts]:
        end = int(np.clip(np.argmin(region[j]) + 4, 2 * knot_periods, last))
        end -= end % knot_periods
        guess = volts[j, :end].reshape(-1, knot_periods).mean(axis=1)
        knots = shoot(rig, limits, guess, knot_periods, max_nfev=max_nfev)
        head = expand(knots, knot_periods)
        y_end = rollout(rig, head)[-1]
        tail, _ = hold_from(rig, limits, y_end[None, :], steps - end, k_gain)
        candidate = np.concatenate([head, tail[0]])
        verdict = verify(rig, limits, candidate)
        tried += 1
        if verdict.ok:
            return Search(True, "shooting", candidate, verdict, bound, tried)
    if transcription is not None:
        result = transcribe(rig, limits, pool, transcription, k_gain)
        tried += result.tried
        if result.voltages is not None:
            return Search(True, "multiple shooting", result.voltages, result.verdict, bound,
                          tried, result.earliest_s)
        return Search(False, "not found", None, best, bound, tried, result.earliest_s)
    return Search(False, "not found", None, best, bound, tried)
