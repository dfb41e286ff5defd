"""Speed against error of the plant's integrators and of SciPy's, on the same problem.

The problem is the one where an integrator's accuracy is well defined: the plant driven
open loop by a recorded command sequence, each command held over one period (zero-order
hold), states compared at the sample times. Every method is restarted at each sample,
as a fixed-step controller around a variable-step solver must be: the held input jumps
there. Errors are the largest difference of the mechanical state (x, x_dot, theta,
theta_dot) from a tight reference over all samples.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.integrate import solve_ivp

from pisc_model.dynamics import energy
from pisc_plant.plant import Plant
from pisc_plant.plant_config import IntegratorParams, PlantConfig

__all__ = [
    "Result",
    "SCIPY_METHODS",
    "energy_drift",
    "methods_for",
    "playback",
    "playback_control",
    "playback_scipy",
    "with_integrator",
]

SCIPY_METHODS = ("RK45", "DOP853", "LSODA", "Radau")
STAGES = {"rk4": 4, "exprk4": 5}


@dataclass(frozen=True)
class Result:
    """One method and setting: states at the samples, wall time, right-hand sides."""

    method: str
    setting: str
    states: np.ndarray  # (samples, state size)
    wall_s: float
    rhs_evaluations: int

    def error(self, reference: np.ndarray) -> float:
        """Largest |difference| of x, x_dot, theta, theta_dot over the samples."""
        return float(np.max(np.abs(self.states[:, :4] - reference[:, :4])))


def with_integrator(config: PlantConfig, method: str, substeps: int) -> Plant:
    return Plant(dataclasses.replace(config, integrator=IntegratorParams(method, substeps)))


def playback(plant: Plant, y0: np.ndarray, commands: np.ndarray, period_s: float) -> Result:
    """The plant's own integrator, one :meth:`Plant.advance` per sample."""
    plant.advance(y0, commands[0], period_s)  # compile and cache before timing
    states = np.empty((len(commands) + 1, plant.size))
    states[0] = y0
    y = y0
    start = time.perf_counter()
    for k, u in enumerate(commands):
        y = plant.advance(y, u, period_s)
        states[k + 1] = y
    wall = time.perf_counter() - start
    cfg = plant.config.integrator
    evaluations = len(commands) * cfg.substeps * STAGES[cfg.method]
    return Result(cfg.method, f"{cfg.substeps} steps/period", states, wall, evaluations)


def playback_scipy(plant: Plant, y0: np.ndarray, commands: np.ndarray, period_s: float,
                   method: str, rtol: float, atol: float) -> Result:
    """``scipy.integrate.solve_ivp`` restarted at every sample on the plant's
    right-hand side (the compiled one, so the comparison is of methods, not of
    right-hand-side cost)."""
    applied = plant.applied(commands)
    states = np.empty((len(commands) + 1, plant.size))
    states[0] = y0
    y = np.asarray(y0, dtype=float)
    evaluations = 0
    start = time.perf_counter()
    for k, u in enumerate(applied):
        u = float(u)
        solution = solve_ivp(lambda t, s, u=u: plant.applied_derivative(s, u), (0.0, period_s),
                             y, method=method, rtol=rtol, atol=atol)
        if not solution.success:
            raise RuntimeError(f"solve_ivp {method} rtol={rtol}: {solution.message} at sample {k}")
        y = solution.y[:, -1]
        if plant.config.models.end_stops:
            y = plant.end_stops(y)
        states[k + 1] = y
        evaluations += solution.nfev
    wall = time.perf_counter() - start
    return Result(f"solve_ivp {method}", f"rtol {rtol:.0e}", states, wall, evaluations)


def playback_control(plant: Plant, y0: np.ndarray, duration_s: float, period_s: float,
                     rtol: float, atol: float) -> Result:
    """python-control's ``input_output_response`` of the plant as a nonlinear system.

    It integrates over the whole run with one ``solve_ivp`` call and an input it
    interpolates between time points, so it applies to scenes without a sampled input:
    here the plant with zero input (the conservative scene).
    """
    import control

    system = control.nlsys(lambda t, x, u, params: plant.applied_derivative(x, 0.0), None,
                           inputs=1, states=plant.size, name="plant")
    n = int(round(duration_s / period_s))
    times = np.arange(n + 1) * period_s
    calls = [0]
    inner = system.updfcn

    def counted(t, x, u, params):
        calls[0] += 1
        return inner(t, x, u, params)

    system.updfcn = counted
    start = time.perf_counter()
    response = control.input_output_response(system, times, np.zeros_like(times), y0,
                                             solve_ivp_method="DOP853",
                                             solve_ivp_kwargs={"rtol": rtol, "atol": atol})
    wall = time.perf_counter() - start
    return Result("control input_output_response", f"DOP853 rtol {rtol:.0e}",
                  np.asarray(response.states).T, wall, calls[0])


def energy_drift(plant: Plant, states: np.ndarray) -> float:
    """Largest |E(t) - E(0)| / |E(0)| of the cart-pole energy (2.54) over the samples."""
    e = energy(plant.config.rig, states[:, 1], states[:, 2], states[:, 3])
    return float(np.max(np.abs(e - e[0])) / abs(e[0]))


def methods_for(plant_config: PlantConfig) -> list[tuple[str, Sequence[int]]]:
    """The plant's integrators and the step counts worth measuring for a scene: a range
    for each method (for rk4 from the smallest stable count when the scene is stiff)
    and always the scene's own setting."""
    stiff = Plant(dataclasses.replace(plant_config, integrator=IntegratorParams("exprk4", 1)))
    rates = -stiff.lam
    own = plant_config.integrator
    exp_counts = {1, 2, 3, 4, 6, 8, 16}
    if rates.size and rates.max() > 0.0:
        # the smallest count the plant accepts (its check), then a few above it
        rk4_min = int(np.ceil(plant_config.loop.period_s * rates.max() / 2.785 * 1.0001))
        rk4_counts = {rk4_min, 16, 20, 32, 64}
    else:
        rk4_counts = {1, 2, 4, 8, 16}
    (exp_counts if own.method == "exprk4" else rk4_counts).add(own.substeps)
    return [("exprk4", sorted(exp_counts)), ("rk4", sorted(rk4_counts))]
