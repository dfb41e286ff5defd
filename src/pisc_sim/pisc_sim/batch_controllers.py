"""The controllers of a batch, compiled: one pass over the rigs per cycle (numba).

:func:`pisc_sim.closed_loop.simulate_batch` runs the estimator, the supervisor and the
current loop of every rig each cycle. Their numpy cores (:mod:`pisc_control`) do that with
about a hundred array operations a cycle, each a pass over all the rigs; here one compiled
loop over the rigs, split between the cores (``prange``), runs for each rig the one-rig
functions the nodes run (:mod:`pisc_control.scalar`: :func:`estimator_step`,
:func:`supervisor_step`, :func:`current_loop_step`, compiled from their Python source).
Those give the numpy cores' bits, and so does their compiled form: numba compiles without
``fastmath``, so no multiply-add is fused and nothing is reassociated, and ``math.sin``
and ``math.cos`` are the C library's in both (``test_batch_controllers`` compares the
compiled pass with the numpy cores over closed-loop runs and hostile inputs).

numba's cache keys an entry on its own file's time stamp only; the compiled pass holds
the code of :mod:`pisc_control.scalar`, so when that file is newer than the cache's
index, the index is removed here before numba reads it and the pass compiles anew.
Experiments (``experiment.kind``) are not compiled: :func:`supported` says so and the
batch then runs the numpy cores.
"""

from __future__ import annotations

import time
from pathlib import Path

import numba
import numpy as np
from numba.extending import register_jitable

from pisc_control import scalar
from pisc_control.estimator import EstimatorState
from pisc_control.scalar import SWING_UP
from pisc_control.supervisor import FAULT_NONE, Supervisor
from pisc_sim.configuration import GraphConfig

__all__ = ["BatchControllers", "supported", "warm_up"]


def _drop_stale_cache() -> None:
    """Remove the compiled pass's cache index when pisc_control.scalar is newer."""
    source = Path(scalar.__file__)
    cache = Path(__file__).parent / "__pycache__"
    try:
        for index in cache.glob(f"{Path(__file__).stem}._cycle-*.nbi"):
            if index.stat().st_mtime < source.stat().st_mtime:
                index.unlink(missing_ok=True)
    except OSError:  # a read-only install: numba then keeps its cache elsewhere
        pass


_drop_stale_cache()
# the one-rig functions and their helpers, callable from compiled code (and unchanged as
# Python functions)
for _function in (scalar._clip, scalar._floor, scalar._sin, scalar._cos, scalar._wrap,
                  scalar._lyapunov_force, scalar._energy_pump_force):
    register_jitable(error_model="numpy")(_function)
_estimator_step = numba.njit(scalar.estimator_step, error_model="numpy")
_supervisor_step = numba.njit(scalar.supervisor_step, error_model="numpy")
_current_loop_step = numba.njit(scalar.current_loop_step, error_model="numpy")


@numba.njit(cache=True, error_model="numpy", parallel=True)
def _cycle(s, c, est_a, est_b, first, est_first, span, oldest, write, x, theta, current,
           x_hist, theta_hist, v_x, v_theta, mode, fault, caught, startup_target, reference,
           integral, force_out, setpoint_out, voltage_out):
    """One cycle of every rig: estimator, supervisor, current loop; state in place."""
    for r in numba.prange(x.shape[0]):
        xr, thr = x[r], theta[r]
        if est_first:
            x_dot = 0.0
            theta_dot = 0.0
        else:
            x_dot, theta_dot = _estimator_step(est_a, est_b, span, xr, thr, x_hist[r, oldest],
                                               theta_hist[r, oldest], v_x[r], v_theta[r])
        x_hist[r, write] = xr
        theta_hist[r, write] = thr
        v_x[r] = x_dot
        v_theta[r] = theta_dot
        force, m, f, k, t, ref = _supervisor_step(
            s, first, xr, x_dot, thr, theta_dot, mode[r], fault[r], caught[r],
            startup_target[r], reference[r])
        mode[r], fault[r], caught[r], startup_target[r], reference[r] = m, f, k, t, ref
        i_d, voltage, integral[r] = _current_loop_step(c, m == scalar.FAULT, force,
                                                       current[r], integral[r])
        force_out[r] = force
        setpoint_out[r] = i_d
        voltage_out[r] = voltage


def supported(config: GraphConfig) -> bool:
    """Whether the compiled cores cover this configuration (all but experiments)."""
    return config.supervisor.experiment.kind == "none"


class BatchControllers:
    """The controllers of ``rigs`` rigs, stepped a cycle at a time by the compiled pass.

    ``estimator`` is the estimator's state before the first cycle (a primed previous
    sample, :func:`pisc_sim.closed_loop.simulate_batch`), flat arrays of ``rigs``
    values; the default is none (the first sample gives zero velocity).
    """

    def __init__(self, config: GraphConfig, supervisor: Supervisor, rigs: int,
                 estimator: EstimatorState | None = None) -> None:
        if not supported(config):
            raise ValueError(f"experiment.kind = {config.supervisor.experiment.kind!r}: "
                             "experiments run on the numpy cores, not the compiled ones")
        period = config.loop.period_s
        self._s = scalar.supervisor_constants(supervisor)
        self._c = scalar.current_loop_constants(config.plant.motor, config.current_loop,
                                                period)
        self._est_a, self._est_b = scalar.estimator_constants(config.estimator, period)
        self._period = period
        self._n = config.estimator.difference_periods
        self._x_hist = np.zeros((rigs, self._n))
        self._theta_hist = np.zeros((rigs, self._n))
        self._v_x = np.zeros(rigs)
        self._v_theta = np.zeros(rigs)
        self._seen = 0  # samples the estimator holds (the same for every rig)
        if estimator is not None and estimator.x_m is not None:
            if estimator.x_past:
                raise ValueError("a primed estimator holds one previous sample")
            self._x_hist[:, 0] = np.broadcast_to(estimator.x_m, (rigs,))
            self._theta_hist[:, 0] = np.broadcast_to(estimator.theta_rad, (rigs,))
            self._v_x[:] = np.broadcast_to(estimator.x_dot_mps, (rigs,))
            self._v_theta[:] = np.broadcast_to(estimator.theta_dot_radps, (rigs,))
            self._seen = 1
        self._cycles = 0
        self._mode = np.full(rigs, SWING_UP, dtype=np.int64)
        self._fault = np.full(rigs, FAULT_NONE, dtype=np.int64)
        self._caught = np.zeros(rigs, dtype=np.bool_)
        self._startup_target = np.zeros(rigs)
        self._reference = np.zeros(rigs)
        self._integral = np.zeros(rigs)

    def step(self, x: np.ndarray, theta: np.ndarray, current: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """One cycle for flat arrays of measurements: (force, mode code, i_d, voltage)."""
        # contiguous and writable (a read-only view would compile a second entry point)
        x, theta, current = (np.require(v, float, ("C", "W")) for v in (x, theta, current))
        rigs = self._v_x.shape[0]
        if not x.shape == theta.shape == current.shape == (rigs,):
            raise ValueError(f"measurements of shape {x.shape}, {theta.shape}, "
                             f"{current.shape}: want ({rigs},) each")
        n = min(self._seen, self._n)  # samples in the difference's window
        span = self._period if n <= 1 else n * self._period
        force, setpoint, voltage = np.empty(rigs), np.empty(rigs), np.empty(rigs)
        _cycle(self._s, self._c, self._est_a, self._est_b, self._cycles == 0, self._seen == 0,
               span, (self._seen - n) % self._n, self._seen % self._n, x, theta, current,
               self._x_hist, self._theta_hist, self._v_x, self._v_theta, self._mode,
               self._fault, self._caught, self._startup_target, self._reference,
               self._integral, force, setpoint, voltage)
        self._seen += 1
        self._cycles += 1
        return force, self._mode.copy(), setpoint, voltage


def warm_up() -> float:
    """Compile (or load from numba's cache) the compiled pass; seconds taken."""
    from pisc_sim.scene import load_scene

    start = time.perf_counter()
    config = load_scene("thesis-rig").config
    controllers = BatchControllers(config, Supervisor(config.supervisor), 2)
    controllers.step(np.zeros(2), np.zeros(2), np.zeros(2))
    return time.perf_counter() - start


if __name__ == "__main__":  # python -m pisc_sim.batch_controllers: ./pisc test warms it
    print(f"pisc_sim.batch_controllers: the compiled batch controllers ready in "
          f"{warm_up():.1f} s", flush=True)
