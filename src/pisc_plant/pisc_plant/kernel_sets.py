"""The entry points of plant sets: every rig its own constants and step
(:func:`pisc_plant.plant_config.plant_set`).

The uniform entry points (:mod:`pisc_plant.kernel_batch`) hold one set of constants and
one operator table as tuples, in registers. A plant set gives each rig its own: 23
constants, the exponential scheme's 13 x 14 operator scalars and a step. They are laid
out in blocks of BLOCK rigs, each block's quantities row after row (``lanes``: block b
holds quantity j of its rig l at [b, j * BLOCK + l]), so that the loop over a block's
rigs reads each quantity from consecutive addresses (vector loads, four rigs at once) at
distances the compiler knows. Measured while building it (10 000 rigs of the full-fidelity layout,
one core, on a machine shared with other work: figures varied by +-15 % between runs):
quantity-major columns over all rigs, (182, rigs), did not vectorise at all (LLVM:
"too many memory checks needed": every row was a pointer of its own); in blocks of
256 rigs, 373 KiB of operators a block, the step took 1.6 to 1.9 times the uniform
one; in blocks of 16 (23 KiB, in the first-level cache for the later substeps) 1.2 to
1.5 times: reading each rig's 1.5 KiB of operators at every call is what a plant set
costs. (Reading a block through once before stepping it did not help.)

:func:`lanes` and :func:`from_lanes` convert to and from that layout,
:func:`exp_tables` computes every rig's operator table into it, :func:`block_step` steps
one block (also the block step of :mod:`pisc_gym.compiled`); the entry points of each
layout are listed in :data:`SET_POINTS` (:func:`pisc_plant.kernel.for_layout`).
"""

from __future__ import annotations

import numba
import numpy as np

from pisc_plant.kernel_batch import in_chunks
from pisc_plant.kernel_jit import compiled, inlined, parallel
from pisc_plant.kernel_operators import (
    N_OPERATORS, OP_WIDTH, armature_operators, armature_rate, step_operators,
)
from pisc_plant.kernel_rhs import stop_at_ends
from pisc_plant.kernel_steps import exprk4_step, rk4_step
from pisc_plant.layout import ARM_FORCE, ARM_FULL, ARM_QUASI_STATIC, P_XMAX, P_XMIN, RK4

__all__ = ["BLOCK", "N_TABLE", "SET_POINTS", "armature_rates", "block_step", "exp_tables",
           "from_lanes", "lanes"]


#: Rigs per block of the per-rig constants and operators (``lanes``); a divisor of
#: CHUNK, so that the parallel entry points' chunks start at a block.
BLOCK = 16

N_TABLE = N_OPERATORS * OP_WIDTH  # operator scalars a rig


def lanes(a: np.ndarray) -> np.ndarray:
    """Per-rig quantities ``a`` (m, rigs) in the kernel's block layout, (blocks, m * BLOCK):
    quantity j of rig k at ``[k // BLOCK, j * BLOCK + k % BLOCK]`` (the last block padded
    with zeros)."""
    m, rigs = a.shape
    blocks = -(-rigs // BLOCK)
    out = np.zeros((blocks, m, BLOCK))
    full = rigs // BLOCK
    out[:full] = a[:, :full * BLOCK].reshape(m, full, BLOCK).transpose(1, 0, 2)
    if full < blocks:
        out[full, :, :rigs - full * BLOCK] = a[:, full * BLOCK:]
    return out.reshape(blocks, m * BLOCK)


def from_lanes(a: np.ndarray, rigs: int) -> np.ndarray:
    """The inverse of :func:`lanes`: (blocks, m * BLOCK) -> (m, rigs)."""
    blocks = a.shape[0]
    m = a.shape[1] // BLOCK
    return a.reshape(blocks, m, BLOCK).transpose(1, 0, 2).reshape(m, blocks * BLOCK)[:, :rigs]


@parallel
def exp_tables(w_ir, w_cur, c_v, lam, steps, out):
    """:func:`exp_coefficients` of every rig k (rates ``lam[k]``, step ``steps[k]``;
    ``w_ir``, ``w_cur``, ``c_v`` are common), rows 0-12 into ``out`` in the layout of
    :func:`lanes` ((blocks, N_TABLE * BLOCK), operator scalar ``op * OP_WIDTH + j``):
    the same numbers, bit for bit. A rig whose step (and rate) equals the previous rig's
    reuses its work."""
    rigs = lam.shape[0]
    for b in numba.prange(out.shape[0]):
        table = np.zeros((15, OP_WIDTH))
        phi_ir = np.empty((2, 4))
        ph = np.empty((2, 8))
        for lane in range(min(BLOCK, rigs - b * BLOCK)):
            k = b * BLOCK + lane
            same_step = lane > 0 and steps[k] == steps[k - 1]
            if not (same_step and lam[k] == lam[k - 1]):
                if not same_step or lam[k] == 0.0:
                    step_operators(w_ir, w_cur, c_v, steps[k], table, phi_ir)  # zeroes
                if lam[k] != 0.0:
                    armature_operators(lam[k], table, ph)
            for op in range(N_OPERATORS):
                for j in range(OP_WIDTH):
                    out[b, (op * OP_WIDTH + j) * BLOCK + lane] = table[op, j]


@compiled
def armature_rates(p, out):
    """:func:`armature_rate` of each column of the constants ``p`` (N_CONSTANTS, rigs)."""
    for k in range(out.shape[0]):
        out[k] = armature_rate(p[:, k])


@inlined
def _constants_at(a, k, stops):
    """Rig k's constants in a block of :func:`lanes` (see :func:`as_constants`)."""
    return (a[k], a[BLOCK + k], a[2 * BLOCK + k], a[3 * BLOCK + k], a[4 * BLOCK + k],
            a[5 * BLOCK + k], a[6 * BLOCK + k], a[7 * BLOCK + k], a[8 * BLOCK + k],
            a[9 * BLOCK + k], a[10 * BLOCK + k], a[11 * BLOCK + k], a[12 * BLOCK + k],
            a[13 * BLOCK + k], a[14 * BLOCK + k], a[15 * BLOCK + k], a[16 * BLOCK + k],
            a[17 * BLOCK + k], a[18 * BLOCK + k], a[19 * BLOCK + k],
            a[P_XMIN * BLOCK + k] if stops else -np.inf,
            a[P_XMAX * BLOCK + k] if stops else np.inf, a[22 * BLOCK + k])


@inlined
def _operator_at(t, op, k):
    b = op * OP_WIDTH * BLOCK + k
    return (t[b], t[b + BLOCK], t[b + 2 * BLOCK], t[b + 3 * BLOCK], t[b + 4 * BLOCK],
            t[b + 5 * BLOCK], t[b + 6 * BLOCK], t[b + 7 * BLOCK], t[b + 8 * BLOCK],
            t[b + 9 * BLOCK], t[b + 10 * BLOCK], t[b + 11 * BLOCK], t[b + 12 * BLOCK],
            t[b + 13 * BLOCK])


@inlined
def _operators_at(t, k):
    """Rig k's operator table in a block of :func:`lanes` (see :func:`as_operators`)."""
    return (_operator_at(t, 0, k), _operator_at(t, 1, k), _operator_at(t, 2, k),
            _operator_at(t, 3, k), _operator_at(t, 4, k), _operator_at(t, 5, k),
            _operator_at(t, 6, k), _operator_at(t, 7, k), _operator_at(t, 8, k),
            _operator_at(t, 9, k), _operator_at(t, 10, k), _operator_at(t, 11, k),
            _operator_at(t, 12, k))


@inlined
def _state_at(b, k):
    return (b[k], b[BLOCK + k], b[2 * BLOCK + k], b[3 * BLOCK + k], b[4 * BLOCK + k],
            b[5 * BLOCK + k], b[6 * BLOCK + k])


@inlined
def _put_at(y, old, moved, b, k):
    """Rig k's new state into the block's columns, or its old one if it did not move (a
    select, not a branch)."""
    b[k] = y[0] if moved else old[0]
    b[BLOCK + k] = y[1] if moved else old[1]
    b[2 * BLOCK + k] = y[2] if moved else old[2]
    b[3 * BLOCK + k] = y[3] if moved else old[3]
    b[4 * BLOCK + k] = y[4] if moved else old[4]
    b[5 * BLOCK + k] = y[5] if moved else old[5]
    b[6 * BLOCK + k] = y[6] if moved else old[6]


@compiled
def block_step(b, us, hs, p, stops, ops, method, substeps, arm, filt, fric):
    """:func:`_lanes` for one block of a plant set: the rigs' states are the columns of
    ``b`` (component j of rig k at ``b[j * BLOCK + k]``), their constants ``p`` and
    operators ``ops`` blocks of :func:`lanes`, their steps ``hs`` (rk4 steps by them;
    exprk4's steps are in its operators). A rig whose step is 0 keeps its state.

    Every index is a multiple of BLOCK plus the rig, so the compiler sees each array as
    one object read at known distances, and the run-time checks of overlap it needs
    before it vectorises are few (one array per quantity were too many).
    """
    numba.literally(arm)
    numba.literally(filt)
    numba.literally(fric)
    rigs = us.shape[0]
    if method == RK4:
        for _ in range(substeps):
            for k in range(rigs):
                h = hs[k]
                y0 = _state_at(b, k)
                pk = _constants_at(p, k, stops)
                y = stop_at_ends(rk4_step(y0, us[k], pk, h, arm, filt, fric), pk)
                _put_at(y, y0, h > 0.0, b, k)
    else:
        for _ in range(substeps):
            for k in range(rigs):
                y0 = _state_at(b, k)
                pk = _constants_at(p, k, stops)
                y = stop_at_ends(exprk4_step(y0, us[k], pk, _operators_at(ops, k), arm, filt,
                                             fric), pk)
                _put_at(y, y0, hs[k] > 0.0, b, k)


@inlined
def _advance_set_rows(ys, us, lo, hi, p, stops, method, substeps, hs, tables, arm, filt, ii,
                      vir, vcur):
    """Advance rows lo..hi of ys (lo a multiple of BLOCK) in place, block by block, each
    rig with its own constants (``p``) and step (``hs``, and ``tables`` for exprk4), both
    in the layout of :func:`lanes`."""
    cols = np.zeros(7 * BLOCK)
    for start in range(lo, hi, BLOCK):
        rigs = min(hi - start, BLOCK)
        block = start // BLOCK
        for k in range(rigs):
            cols[k] = ys[start + k, 0]
            cols[BLOCK + k] = ys[start + k, 1]
            cols[2 * BLOCK + k] = ys[start + k, 2]
            cols[3 * BLOCK + k] = ys[start + k, 3]
            if ii >= 0:
                cols[4 * BLOCK + k] = ys[start + k, ii]
            if vir >= 0:
                cols[5 * BLOCK + k] = ys[start + k, vir]
                cols[6 * BLOCK + k] = ys[start + k, vcur]
        block_step(cols, us[start:start + rigs], hs[start:start + rigs], p[block], stops,
                   tables[block], method, substeps, arm, filt, True)
        for k in range(rigs):
            ys[start + k, 0] = cols[k]
            ys[start + k, 1] = cols[BLOCK + k]
            ys[start + k, 2] = cols[2 * BLOCK + k]
            ys[start + k, 3] = cols[3 * BLOCK + k]
            if ii >= 0:
                ys[start + k, ii] = cols[4 * BLOCK + k]
            if vir >= 0:
                ys[start + k, vir] = cols[5 * BLOCK + k]
                ys[start + k, vcur] = cols[6 * BLOCK + k]


# One row-range and one parallel entry point per layout, as above.
@compiled
def _set_full_filters(ys, us, lo, hi, p, stops, method, substeps, hs, tables):
    _advance_set_rows(ys, us, lo, hi, p, stops, method, substeps, hs, tables, ARM_FULL, True,
                      4, 5, 6)


@compiled
def _set_full(ys, us, lo, hi, p, stops, method, substeps, hs, tables):
    _advance_set_rows(ys, us, lo, hi, p, stops, method, substeps, hs, tables, ARM_FULL, False,
                      4, -1, -1)


@compiled
def _set_quasi_static_filters(ys, us, lo, hi, p, stops, method, substeps, hs, tables):
    _advance_set_rows(ys, us, lo, hi, p, stops, method, substeps, hs, tables,
                      ARM_QUASI_STATIC, True, -1, 4, 5)


@compiled
def _set_quasi_static(ys, us, lo, hi, p, stops, method, substeps, hs, tables):
    _advance_set_rows(ys, us, lo, hi, p, stops, method, substeps, hs, tables,
                      ARM_QUASI_STATIC, False, -1, -1, -1)


@compiled
def _set_force_filters(ys, us, lo, hi, p, stops, method, substeps, hs, tables):
    _advance_set_rows(ys, us, lo, hi, p, stops, method, substeps, hs, tables, ARM_FORCE, True,
                      -1, 4, 5)


@compiled
def _set_force(ys, us, lo, hi, p, stops, method, substeps, hs, tables):
    _advance_set_rows(ys, us, lo, hi, p, stops, method, substeps, hs, tables, ARM_FORCE, False,
                      -1, -1, -1)


@parallel
def _many_set_full_filters(ys, us, p, stops, method, substeps, hs, tables):
    in_chunks(_set_full_filters, ys, us, p, stops, method, substeps, hs, tables)


@parallel
def _many_set_full(ys, us, p, stops, method, substeps, hs, tables):
    in_chunks(_set_full, ys, us, p, stops, method, substeps, hs, tables)


@parallel
def _many_set_quasi_static_filters(ys, us, p, stops, method, substeps, hs, tables):
    in_chunks(_set_quasi_static_filters, ys, us, p, stops, method, substeps, hs, tables)


@parallel
def _many_set_quasi_static(ys, us, p, stops, method, substeps, hs, tables):
    in_chunks(_set_quasi_static, ys, us, p, stops, method, substeps, hs, tables)


@parallel
def _many_set_force_filters(ys, us, p, stops, method, substeps, hs, tables):
    in_chunks(_set_force_filters, ys, us, p, stops, method, substeps, hs, tables)


@parallel
def _many_set_force(ys, us, p, stops, method, substeps, hs, tables):
    in_chunks(_set_force, ys, us, p, stops, method, substeps, hs, tables)


SET_POINTS = {
    (ARM_FULL, True): (_set_full_filters, _many_set_full_filters),
    (ARM_FULL, False): (_set_full, _many_set_full),
    (ARM_QUASI_STATIC, True): (_set_quasi_static_filters, _many_set_quasi_static_filters),
    (ARM_QUASI_STATIC, False): (_set_quasi_static, _many_set_quasi_static),
    (ARM_FORCE, True): (_set_force_filters, _many_set_force_filters),
    (ARM_FORCE, False): (_set_force, _many_set_force),
}
