"""The fit's statistics: when to stop (:func:`within_standard_error`, :func:`stalled`), the
estimates' covariance (:func:`covariance`, with its quantisation floor
:func:`quantisation_meat`), and the pairs the data cannot tell apart
(:func:`inseparable`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from pisc_robust.identify_data import QUANTISATION_RMS, IdentifyError
from pisc_robust.identify_model import Problem

__all__ = ["STALL_FRACTION", "STALL_ITERATIONS", "STOP_FRACTION", "covariance", "inseparable",
           "quantisation_meat", "stalled", "within_standard_error"]

#: A fit stops when its next Gauss-Newton step is under this fraction of every unknown's
#: standard error (:func:`within_standard_error`)
STOP_FRACTION = 0.01
#: ... or when its last STALL_ITERATIONS iterations gained less than a move of
#: STALL_FRACTION of a standard error would (:func:`stalled`)
STALL_ITERATIONS = 5
STALL_FRACTION = 0.25


def covariance(problem: Problem, jac: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, int]:
    """Cluster-robust covariance of the fitted parameters (scaled), over segments, and
    the degrees of freedom of its t quantile.

    ``jac`` is the projected Jacobian at the optimum (the states eliminated), so
    ``(J^T J)^-1`` is the parameters' block of the full problem's inverse, and each
    segment's score ``g_s = J_s^T r_s`` is its parameters' score (its own states' scores
    vanish at their optimum). The sandwich ``(J^T J)^-1 (sum_s h_s h_s^T) (J^T J)^-1``
    takes the scores as the jackknife over segments does (CR3): ``h_s = (I - H_ss)^-1``
    applied to the segment's residuals, ``H_ss`` its leverage, which is
    ``h_s = B (B - J_s^T J_s)^-1 g_s`` with ``B = J^T J`` (Woodbury), times
    ``(n - 1) / n``: with a few dozen segments, the plain sandwich is too narrow.
    """
    bread = jac.T @ jac
    inverse = np.linalg.pinv(bread, rcond=1e-14, hermitian=True)
    n_seg = problem.seg.count
    scores = []
    for s in range(n_seg):
        rows = problem.segment_rows(s)
        js = jac[rows]
        g = js.T @ r[rows]
        try:
            h = bread @ np.linalg.solve(bread - js.T @ js, g)
        except np.linalg.LinAlgError:
            h = g
        scores.append(h)
    scores = np.array(scores)
    meat = scores.T @ scores * ((n_seg - 1) / max(n_seg, 1))
    return inverse @ (meat + quantisation_meat(problem, jac)) @ inverse, max(n_seg - 1, 1)


def quantisation_meat(problem: Problem, jac: np.ndarray) -> np.ndarray:
    """The quantisation floor of the covariance's meat: ``sigma_q^2 sum_c s_c s_c^T``.

    A quantised sensor's error is a function of the true value: every sample a channel
    reads at one code shares (nearly) the same error ``e_c``, uniform over the step
    (``sigma_q^2 = 1/12`` of a step squared). A signal held at one level (the current at
    its limit, the pendulum hanging still) is at the same code in every segment, so its
    error is the same in all of them: the estimate moves by ``-B^-1 J^T dr`` and the
    sandwich over segments, which sees only what differs between segments, never sees
    it. Taking each (channel, code) as one such error, independent of the others,
    adds ``B^-1 (sigma_q^2 sum_c s_c s_c^T) B^-1`` to the covariance, where
    ``s_c = sum over the held rows read at code c of w J_row`` (``w`` the channel's
    weight: the rows are weighted residuals, so an error of ``e`` steps moves a row by
    ``w e``). Only held rows count (:meth:`Problem.row_codes`: the code read for at
    least :data:`pisc_robust.identify_model.HELD_SAMPLES` samples in a row): a signal passing through a code, or
    swinging about it, reads it at true values spread over the step, whose errors are
    not shared (the sandwich sees them), and counting them as one error would swamp
    what depends on them (J_m, through the swinging pendulum's encoder)."""
    codes, channel, held = problem.row_codes()
    if not held.any():
        return np.zeros((jac.shape[1], jac.shape[1]))
    weight = problem.weights[channel[held]]
    group = np.unique(np.column_stack([channel[held], codes[held]]), axis=0,
                      return_inverse=True)[1]
    group = np.asarray(group).reshape(-1)
    sums = np.zeros((int(group.max()) + 1, jac.shape[1]))
    np.add.at(sums, group, jac[held] * weight[:, None])
    return QUANTISATION_RMS ** 2 * (sums.T @ sums)



def within_standard_error(jac: np.ndarray, r: np.ndarray, z: np.ndarray,
                           low: np.ndarray, high: np.ndarray,
                           fraction: float | None = None) -> bool:
    """Whether the Gauss-Newton step from ``z`` (kept inside the bounds) moves every
    unknown by less than ``fraction`` (default :data:`STOP_FRACTION`) of its standard
    error: the statistical stopping rule of a least-squares fit (after Bates and Watts,
    *Technometrics* 23 (1981), the relative offset), which an ``ftol`` on the cost is
    not. Along a valley (R and J_m, docs/identification.md) each step lowers a cost of
    some 10^4 by 10^-4 or so: far below what the data can tell, and an ``ftol`` of 1e-9
    kept such fits going until they ran out of evaluations. The standard errors here are
    Gauss-Newton's, ``s^2 (J^T J)^-1`` with ``s^2`` the residuals' mean square (cheap at
    every step; the reported intervals use the sandwich)."""
    fraction = STOP_FRACTION if fraction is None else fraction
    n, p = jac.shape
    if n <= p:
        return False
    try:
        step, *_ = np.linalg.lstsq(jac, -r, rcond=None)
        # an unknown on a bound that the step would take past it stays there, and the
        # step is that of the others alone (the bound's active set)
        held = ((z <= low) & (step < 0.0)) | ((z >= high) & (step > 0.0))
        if held.any():
            step = np.zeros(p)
            if not held.all():
                step[~held], *_ = np.linalg.lstsq(jac[:, ~held], -r, rcond=None)
        inverse = np.linalg.pinv(jac.T @ jac, rcond=1e-14, hermitian=True)
    except np.linalg.LinAlgError:
        return False
    step = np.clip(z + step, low, high) - z
    s2 = float(r @ r) / (n - p)
    std = np.sqrt(np.maximum(np.diag(inverse), 0.0) * s2)
    return bool(np.all(np.abs(step) <= fraction * std))


def stalled(costs: Sequence[float], dof: int) -> bool:
    """Whether the last :data:`STALL_ITERATIONS` iterations of a fit (``costs``: the sum
    of squared residuals after each) together lowered it by less than a move of
    :data:`STALL_FRACTION` of a standard error does: in the Gauss-Newton model a move of
    ``f`` standard errors (the Mahalanobis distance in ``s^2 (J^T J)^-1``) changes the
    cost by ``f^2 s^2``, ``s^2`` the residuals' mean square (``dof`` degrees of freedom).
    A fit whose Gauss-Newton steps promise more than they deliver, step after step, is
    at the resolution of its own residuals (each segment's initial state is solved
    anew at every evaluation, to a tolerance): through the driver, a draw whose last
    pass went on for 100 evaluations gained 0.01-0.2 of a cost of 26,071 an iteration
    while its Gauss-Newton step stayed 0.16-0.92 of the delay's standard error."""
    if len(costs) <= STALL_ITERATIONS or dof <= 0:
        return False
    s2 = costs[-1] / dof
    return costs[-1 - STALL_ITERATIONS] - costs[-1] < STALL_FRACTION ** 2 * s2


def inseparable(problem: Problem, z: np.ndarray) -> str:
    """For a fit that did not converge: the pairs of parameters whose estimates correlate
    beyond 0.95 at its last point (Gauss-Newton's (J^T J)^-1), the usual reason (a valley
    along which the cost barely changes), as text to add to the error."""
    try:
        jac = problem.jacobian(z)
        cov = np.linalg.pinv(jac.T @ jac, rcond=1e-14, hermitian=True)
    except (IdentifyError, np.linalg.LinAlgError, ValueError):
        return ""
    d = np.sqrt(np.maximum(np.diag(cov), 1e-300))
    corr = cov / np.outer(d, d)
    pairs = [f"{problem.fit[a].key} and {problem.fit[b].key} (correlation {corr[a, b]:+.3f})"
             for a in range(problem.p) for b in range(a + 1, problem.p)
             if abs(corr[a, b]) > 0.95]
    if not pairs:
        return ""
    return ("; these data cannot tell apart " + ", ".join(pairs)
            + ": fit one of each pair, the other known (--fit, --config)")

