"""pisc_gym_catchable: which of the catch task's starts can be caught at all?

    pisc_gym_catchable [--start arriving|rest] [--starts 300] [--seed 2147483648]

(a few seconds a start on a loaded machine: two linear programmes and the flight)

Before asking a learner for a rate, ask the task: for each start of ``pisc/Catch-v0``
(``thesis-rig`` rigs, drawn as the vector environment draws them from ``--seed``), does
any armature voltage sequence catch it, within the task's rules (the cart inside the
safe range at every sample, |theta| < 0.05 rad over the episode's last second) and the
actuator's (|u| <= the bridge's full scale, |i| <= the current loop's limit)?

Two answers, one a bound each way:

1. **The linear programme** (:func:`plan`): the rig's plant linearised about upright
   at rest (its own M, m, l, I, motor, viscous frictions, the armature current a state;
   one period of the compiled kernel, :class:`pisc_plant.plant.Plant`, differenced),
   the voltage held one period, the states at every sample as unknowns tied by the
   dynamics; every rule above is linear in them, so whether an input exists is a linear
   programme (``scipy.optimize.linprog``, HiGHS). It is solved with the track's bound
   relaxed by a slack s >= 0 and s minimised: s = 0 is a plan that keeps the track; s > 0
   (or no plan at all) says by how much even the best input leaves it. Exact for the
   linear model; the true pendulum's sin and cos (about 1.5 % at 0.3 rad) and the cart's
   Coulomb friction are left out.
2. **The plan flown** (:func:`fly`): a start with a plan is flown through the task's own
   environment (``action="voltage"``: the quantised bridge, the command latency, the
   nonlinear plant, friction with its Coulomb part), the voltage the plan's plus an LQR
   correction on the true state (``info["true_state"]``) towards the plan's states; a
   start it catches is catchable, shown by an input.

The share caught by (2) is a lower bound on what any policy can reach on the task, and
the share with a plan (1) an upper bound up to the linearisation and the solver (a
programme HiGHS cannot settle counts as one without a plan). docs/gym.md ("What the
catch task allows") has the figures.
"""

from __future__ import annotations

import math

import numpy as np

from pisc_gym.learn import CAUGHT_RAD, HOLD_S

__all__ = ["Plan", "fly", "linearise", "plan", "plans", "tracking_gain"]

STATE = 5  # x, x_dot, theta, theta_dot, i
MARGIN_M = 0.005  # the plan flown keeps this far inside the track,
FLY_SHARE = 0.85  # within this share of the voltage and current limits


class Plan:
    """One start's linear programme: ``slack_m`` (0: the track kept), the voltages (K,)
    and states (K + 1, 5) of the plan (None without one)."""

    def __init__(self, slack_m: float, voltages: np.ndarray | None,
                 states: np.ndarray | None) -> None:
        self.slack_m = slack_m
        self.voltages = voltages
        self.states = states

    @property
    def keeps_track(self) -> bool:
        return self.voltages is not None and self.slack_m <= 1e-7


def linearise(plant, period_s: float, step: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
    """(A_d (5, 5), B_d (5,)): one period of ``plant`` (a 5-state compiled plant) about
    upright at rest, by forward differences of :meth:`Plant.advance`."""
    y0 = np.zeros((1, STATE))
    base = plant.advance(y0, np.zeros(1), period_s)[0]
    ad = np.empty((STATE, STATE))
    for j in range(STATE):
        y = y0.copy()
        y[0, j] = step
        ad[:, j] = (plant.advance(y, np.zeros(1), period_s)[0] - base) / step
    bd = (plant.advance(y0, np.full(1, step), period_s)[0] - base) / step
    return ad, bd


def plan(ad: np.ndarray, bd: np.ndarray, y0: np.ndarray, steps: int, hold_from: int,
         track: tuple[float, float], voltage_v: float, current_a: float,
         hold_rad: float = CAUGHT_RAD) -> Plan:
    """The linear programme of the module's docstring for one start ``y0`` (5,): states
    y_0..y_K, voltages u_0..u_{K-1} and the slack s; y_{k+1} = A_d y_k + B_d u_k;
    track[0] - s <= x_k <= track[1] + s, |theta_k| <= pi / 2 and, from ``hold_from``,
    |theta_k| <= ``hold_rad``; |i_k| <= ``current_a``; |u_k| <= ``voltage_v``; minimise
    s. No solution (:attr:`Plan.slack_m` infinite): HiGHS proved that the current and
    voltage cannot hold the angle at all, or could not settle the programme (the
    unstable mode of a falling pendulum grows as e^(9.3 t)); either way no plan."""
    import scipy.sparse as sparse
    from scipy.optimize import linprog

    n_y = STATE * (steps + 1)
    n = n_y + steps + 1
    slack = n - 1
    # the dynamics: y_0 = y0; y_{k+1} - A_d y_k - B_d u_k = 0
    k = np.arange(steps)
    rows = [np.arange(STATE)]
    cols = [np.arange(STATE)]
    vals = [np.ones(STATE)]
    for j in range(STATE):
        r = STATE * (k + 1) + j
        rows.append(r)
        cols.append(STATE * (k + 1) + j)
        vals.append(np.ones(steps))
        for m in range(STATE):
            rows.append(r)
            cols.append(STATE * k + m)
            vals.append(np.full(steps, -ad[j, m]))
        rows.append(r)
        cols.append(n_y + k)
        vals.append(np.full(steps, -bd[j]))
    a_eq = sparse.csr_matrix((np.concatenate(vals), (np.concatenate(rows),
                                                    np.concatenate(cols))), shape=(n_y, n))
    b_eq = np.zeros(n_y)
    b_eq[:STATE] = y0
    # the track, softened by the slack: x_k - s <= high, -x_k - s <= -low
    x = STATE * np.arange(1, steps + 1)
    a_ub = sparse.csr_matrix((
        np.r_[np.ones(steps), -np.ones(steps), -np.ones(steps), -np.ones(steps)],
        (np.r_[k, k, steps + k, steps + k], np.r_[x, np.full(steps, slack), x,
                                                  np.full(steps, slack)])),
        shape=(2 * steps, n))
    b_ub = np.r_[np.full(steps, track[1]), np.full(steps, -track[0])]
    bounds = np.empty((n, 2))
    theta = np.where(np.arange(steps + 1) >= hold_from, hold_rad, math.pi / 2)
    bounds[:n_y] = (-np.inf, np.inf)
    bounds[2:n_y:STATE] = np.column_stack([-theta, theta])
    bounds[4:n_y:STATE] = (-current_a, current_a)
    bounds[:STATE] = (-np.inf, np.inf)  # the start is fixed by the equalities
    bounds[n_y:n_y + steps] = (-voltage_v, voltage_v)
    bounds[slack] = (0.0, np.inf)
    c = np.zeros(n)
    c[slack] = 1.0
    res = linprog(c, A_ub=a_ub, b_ub=b_ub, A_eq=a_eq, b_eq=b_eq, bounds=bounds,
                  method="highs")
    if res.status != 0:  # infeasible, or unresolved: the unstable mode grows e^(9.3 t)
        return Plan(math.inf, None, None)
    return Plan(float(res.x[slack]), res.x[n_y:n_y + steps].copy(),
                res.x[:n_y].reshape(steps + 1, STATE).copy())

def tracking_gain(ad: np.ndarray, bd: np.ndarray) -> np.ndarray:
    """Discrete LQR gain (5,) of the voltage on the 5-state linear model: Q = diag(1 /
    (0.01 m, 0.1 m/s, 0.01 rad, 0.1 rad/s, 1 A)^2), R = 1 / (5 V)^2."""
    from scipy.linalg import solve_discrete_are

    q = np.diag(1.0 / np.square([0.01, 0.1, 0.01, 0.1, 1.0]))
    r = np.array([[1.0 / 5.0**2]])
    b = bd[:, None]
    p = solve_discrete_are(ad, b, q, r)
    return np.linalg.solve(r + b.T @ p @ b, b.T @ p @ ad)[0]


def plans(start: str, starts: int, seed: int, report: bool = False):
    """Each start's plans and the gains to track them: (env, obs, info, plans, gains
    (starts, 5)) of a voltage-action catch environment reset with ``seed``; a start's
    plans are (the best, the one to fly): the best within the limits themselves, and one
    :data:`MARGIN_M` inside the track, within :data:`FLY_SHARE` of the voltage and the
    current and within half the catch's angle over the last second, when that exists."""
    from pisc_analysis.feasibility import exact_plant
    from pisc_gym.learn import environment
    from pisc_plant.plant import Plant

    env, obs, info = environment(starts, seed, action="voltage", start=start)
    task = env.task
    steps = task.episode_steps
    hold_from = steps - int(round(HOLD_S / task.period_s))
    rig = info["rig"]
    out, gains = [], np.zeros((starts, STATE))
    for k in range(starts):
        values = {name: float(rig[name][k]) for name in task.physical_names}
        # the linear model: the Coulomb friction's smoothed step is no slope of the physics
        linear = Plant(exact_plant(task.plant, {**values, "friction.cart_coulomb_n": 0.0}))
        ad, bd = linearise(linear, task.period_s)
        y0 = info["true_state"][k]
        best = plan(ad, bd, y0, steps, hold_from, task.safe_range, task.voltage_limit_v,
                    task.current_limit_a)
        flown = None
        if best.keeps_track:  # the plan to fly keeps a margin for the feedback
            low, high = task.safe_range
            flown = plan(ad, bd, y0, steps, hold_from, (low + MARGIN_M, high - MARGIN_M),
                         FLY_SHARE * task.voltage_limit_v, FLY_SHARE * task.current_limit_a,
                         0.5 * CAUGHT_RAD)
        out.append((best, flown if flown is not None and flown.keeps_track else best))
        gains[k] = tracking_gain(ad, bd)
        if report and (k + 1) % 100 == 0:
            print(f"planned {k + 1} of {starts}", flush=True)
    return env, obs, info, out, gains


def fly(env, obs: np.ndarray, info: dict, plans_: list[tuple[Plan, Plan]],
        gains: np.ndarray) -> np.ndarray:
    """Each plan flown through ``env`` (just reset, voltage action), the plan's voltage
    plus the LQR correction ``-gains . (y - y_plan)`` on the true state: caught (starts,).
    A start without a plan that keeps the track gets the LQR about the plan-less upright
    (it is not counted caught unless it is)."""
    from pisc_gym.learn import run

    steps = env.task.episode_steps
    n = len(plans_)
    u_ref = np.zeros((n, steps))
    y_ref = np.zeros((n, steps + 1, STATE))
    y_ref[:, :, 0] = env.task.middle_m
    for k, (best, flown) in enumerate(plans_):
        if best.keeps_track:
            u_ref[k], y_ref[k] = flown.voltages, flown.states
    return run(env, obs, info, lambda j, o, inf: u_ref[:, j] - np.sum(
        gains * (inf["true_state"] - y_ref[:, j]), axis=1))[1]
