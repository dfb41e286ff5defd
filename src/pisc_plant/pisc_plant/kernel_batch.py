"""The uniform entry points: rigs that share one set of constants and one step, as rows
of a state array, stepped by the vectorised loop over rigs, in parallel chunks for a
batch.

:func:`_lanes` is the loop (compiled once per layout), :func:`_advance_rows` moves rows
into its columns and back; each layout has an entry point for rows (``_advance_*``)
and one that shares chunks of :data:`CHUNK` rows between the cores (``_many_*``),
listed in :data:`ENTRY_POINTS` (:func:`pisc_plant.kernel.for_layout`).
"""

from __future__ import annotations

import numba
import numpy as np

from pisc_plant.kernel_jit import compiled, inlined, parallel
from pisc_plant.kernel_rhs import as_constants, stop_at_ends
from pisc_plant.kernel_steps import as_operators, exprk4_step, rk4_step
from pisc_plant.layout import ARM_FORCE, ARM_FULL, ARM_QUASI_STATIC, RK4

__all__ = ["CHUNK", "ENTRY_POINTS", "in_chunks"]


@inlined
def _put(y, k, b0, b1, b2, b3, b4, b5, b6):
    b0[k] = y[0]
    b1[k] = y[1]
    b2[k] = y[2]
    b3[k] = y[3]
    b4[k] = y[4]
    b5[k] = y[5]
    b6[k] = y[6]


@compiled
def _lanes(b0, b1, b2, b3, b4, b5, b6, us, p, ops, method, substeps, h, arm, filt, fric):
    """Advance the rigs whose states are the columns of the rows b0..b6 (one row per
    state component, one column per rig): the loop over rigs is the vectorised one.

    Compiled once per layout: ``literally`` makes ``arm``, ``filt`` and ``fric`` (the
    Coulomb term) constants of each compilation. (Inlined into the entry points instead,
    as the helpers below it are, numba copied the whole step's intermediate code at every
    level of inlining: the kernel took 14 minutes to compile.)
    """
    numba.literally(arm)
    numba.literally(filt)
    numba.literally(fric)
    rigs = us.shape[0]
    if method == RK4:
        for _ in range(substeps):
            for k in range(rigs):
                y = rk4_step((b0[k], b1[k], b2[k], b3[k], b4[k], b5[k], b6[k]), us[k], p, h,
                             arm, filt, fric)
                y = stop_at_ends(y, p)
                _put(y, k, b0, b1, b2, b3, b4, b5, b6)
    else:
        for _ in range(substeps):
            for k in range(rigs):
                y = exprk4_step((b0[k], b1[k], b2[k], b3[k], b4[k], b5[k], b6[k]), us[k], p,
                                ops, arm, filt, fric)
                y = stop_at_ends(y, p)
                _put(y, k, b0, b1, b2, b3, b4, b5, b6)


@inlined
def _advance_rows(ys, us, lo, hi, p, stops, method, substeps, h, coef, arm, filt, ii, vir,
                  vcur, fric):
    """Advance rows lo..hi of ys (one rig per row, the layout's order) in place."""
    rigs = hi - lo
    cols = np.zeros((7, rigs))
    for k in range(rigs):
        cols[0, k] = ys[lo + k, 0]
        cols[1, k] = ys[lo + k, 1]
        cols[2, k] = ys[lo + k, 2]
        cols[3, k] = ys[lo + k, 3]
        if ii >= 0:
            cols[4, k] = ys[lo + k, ii]
        if vir >= 0:
            cols[5, k] = ys[lo + k, vir]
            cols[6, k] = ys[lo + k, vcur]
    _lanes(cols[0], cols[1], cols[2], cols[3], cols[4], cols[5], cols[6], us[lo:hi],
           as_constants(p, stops), as_operators(coef), method, substeps, h, arm, filt, fric)
    for k in range(rigs):
        ys[lo + k, 0] = cols[0, k]
        ys[lo + k, 1] = cols[1, k]
        ys[lo + k, 2] = cols[2, k]
        ys[lo + k, 3] = cols[3, k]
        if ii >= 0:
            ys[lo + k, ii] = cols[4, k]
        if vir >= 0:
            ys[lo + k, vir] = cols[5, k]
            ys[lo + k, vcur] = cols[6, k]


# One set of entry points per layout, and one more with the Coulomb term
# (models.friction = coulomb), written out: the layout's numbers must be
# constants where _advance_rows is inlined. (Closures over the numbers would say this in
# fewer lines, but numba's cache gives closures of one function the same symbol names,
# and two of them loaded into one process corrupted each other: a segfault.)
@compiled
def _advance_full_filters(ys, us, lo, hi, p, stops, method, substeps, h, coef):
    _advance_rows(ys, us, lo, hi, p, stops, method, substeps, h, coef,
                  ARM_FULL, True, 4, 5, 6, False)


@compiled
def _advance_full_filters_coulomb(ys, us, lo, hi, p, stops, method, substeps, h, coef):
    _advance_rows(ys, us, lo, hi, p, stops, method, substeps, h, coef,
                  ARM_FULL, True, 4, 5, 6, True)


@compiled
def _advance_full(ys, us, lo, hi, p, stops, method, substeps, h, coef):
    _advance_rows(ys, us, lo, hi, p, stops, method, substeps, h, coef,
                  ARM_FULL, False, 4, -1, -1, False)


@compiled
def _advance_full_coulomb(ys, us, lo, hi, p, stops, method, substeps, h, coef):
    _advance_rows(ys, us, lo, hi, p, stops, method, substeps, h, coef,
                  ARM_FULL, False, 4, -1, -1, True)


@compiled
def _advance_quasi_static_filters(ys, us, lo, hi, p, stops, method, substeps, h, coef):
    _advance_rows(ys, us, lo, hi, p, stops, method, substeps, h, coef,
                  ARM_QUASI_STATIC, True, -1, 4, 5, False)


@compiled
def _advance_quasi_static_filters_coulomb(ys, us, lo, hi, p, stops, method, substeps, h, coef):
    _advance_rows(ys, us, lo, hi, p, stops, method, substeps, h, coef,
                  ARM_QUASI_STATIC, True, -1, 4, 5, True)


@compiled
def _advance_quasi_static(ys, us, lo, hi, p, stops, method, substeps, h, coef):
    _advance_rows(ys, us, lo, hi, p, stops, method, substeps, h, coef,
                  ARM_QUASI_STATIC, False, -1, -1, -1, False)


@compiled
def _advance_quasi_static_coulomb(ys, us, lo, hi, p, stops, method, substeps, h, coef):
    _advance_rows(ys, us, lo, hi, p, stops, method, substeps, h, coef,
                  ARM_QUASI_STATIC, False, -1, -1, -1, True)


@compiled
def _advance_force_filters(ys, us, lo, hi, p, stops, method, substeps, h, coef):
    _advance_rows(ys, us, lo, hi, p, stops, method, substeps, h, coef,
                  ARM_FORCE, True, -1, 4, 5, False)


@compiled
def _advance_force_filters_coulomb(ys, us, lo, hi, p, stops, method, substeps, h, coef):
    _advance_rows(ys, us, lo, hi, p, stops, method, substeps, h, coef,
                  ARM_FORCE, True, -1, 4, 5, True)


@compiled
def _advance_force(ys, us, lo, hi, p, stops, method, substeps, h, coef):
    _advance_rows(ys, us, lo, hi, p, stops, method, substeps, h, coef,
                  ARM_FORCE, False, -1, -1, -1, False)


@compiled
def _advance_force_coulomb(ys, us, lo, hi, p, stops, method, substeps, h, coef):
    _advance_rows(ys, us, lo, hi, p, stops, method, substeps, h, coef,
                  ARM_FORCE, False, -1, -1, -1, True)


# Rigs per task of the parallel loop: the columns of a task (7 x 256 doubles, 14 KiB)
# stay in the core's first-level cache through the substeps.
CHUNK = 256


@inlined
def in_chunks(advance, ys, us, p, stops, method, substeps, a, b):
    """``advance`` over the rows of ``ys`` in tasks of :data:`CHUNK` rigs, in parallel;
    ``a`` and ``b`` are the advance's own last arguments (the step and its coefficients,
    or a plant set's steps and tables)."""
    rows = ys.shape[0]
    for c in numba.prange((rows + CHUNK - 1) // CHUNK):
        advance(ys, us, c * CHUNK, min(rows, (c + 1) * CHUNK), p, stops, method, substeps,
                a, b)


@parallel
def _many_full_filters(ys, us, p, stops, method, substeps, h, coef):
    in_chunks(_advance_full_filters, ys, us, p, stops, method, substeps, h, coef)


@parallel
def _many_full_filters_coulomb(ys, us, p, stops, method, substeps, h, coef):
    in_chunks(_advance_full_filters_coulomb, ys, us, p, stops, method, substeps, h, coef)


@parallel
def _many_full(ys, us, p, stops, method, substeps, h, coef):
    in_chunks(_advance_full, ys, us, p, stops, method, substeps, h, coef)


@parallel
def _many_full_coulomb(ys, us, p, stops, method, substeps, h, coef):
    in_chunks(_advance_full_coulomb, ys, us, p, stops, method, substeps, h, coef)


@parallel
def _many_quasi_static_filters(ys, us, p, stops, method, substeps, h, coef):
    in_chunks(_advance_quasi_static_filters, ys, us, p, stops, method, substeps, h, coef)


@parallel
def _many_quasi_static_filters_coulomb(ys, us, p, stops, method, substeps, h, coef):
    in_chunks(_advance_quasi_static_filters_coulomb, ys, us, p, stops, method, substeps, h, coef)


@parallel
def _many_quasi_static(ys, us, p, stops, method, substeps, h, coef):
    in_chunks(_advance_quasi_static, ys, us, p, stops, method, substeps, h, coef)


@parallel
def _many_quasi_static_coulomb(ys, us, p, stops, method, substeps, h, coef):
    in_chunks(_advance_quasi_static_coulomb, ys, us, p, stops, method, substeps, h, coef)


@parallel
def _many_force_filters(ys, us, p, stops, method, substeps, h, coef):
    in_chunks(_advance_force_filters, ys, us, p, stops, method, substeps, h, coef)


@parallel
def _many_force_filters_coulomb(ys, us, p, stops, method, substeps, h, coef):
    in_chunks(_advance_force_filters_coulomb, ys, us, p, stops, method, substeps, h, coef)


@parallel
def _many_force(ys, us, p, stops, method, substeps, h, coef):
    in_chunks(_advance_force, ys, us, p, stops, method, substeps, h, coef)


@parallel
def _many_force_coulomb(ys, us, p, stops, method, substeps, h, coef):
    in_chunks(_advance_force_coulomb, ys, us, p, stops, method, substeps, h, coef)


# (armature, filters, Coulomb friction): the uniform entry points; a plant set's above
# take the Coulomb term always (each rig has its own F_c)
ENTRY_POINTS = {
    (ARM_FULL, True, False): (_advance_full_filters, _many_full_filters),
    (ARM_FULL, True, True): (_advance_full_filters_coulomb, _many_full_filters_coulomb),
    (ARM_FULL, False, False): (_advance_full, _many_full),
    (ARM_FULL, False, True): (_advance_full_coulomb, _many_full_coulomb),
    (ARM_QUASI_STATIC, True, False): (_advance_quasi_static_filters,
                                      _many_quasi_static_filters),
    (ARM_QUASI_STATIC, True, True): (_advance_quasi_static_filters_coulomb,
                                     _many_quasi_static_filters_coulomb),
    (ARM_QUASI_STATIC, False, False): (_advance_quasi_static, _many_quasi_static),
    (ARM_QUASI_STATIC, False, True): (_advance_quasi_static_coulomb,
                                      _many_quasi_static_coulomb),
    (ARM_FORCE, True, False): (_advance_force_filters, _many_force_filters),
    (ARM_FORCE, True, True): (_advance_force_filters_coulomb, _many_force_filters_coulomb),
    (ARM_FORCE, False, False): (_advance_force, _many_force),
    (ARM_FORCE, False, True): (_advance_force_coulomb, _many_force_coulomb),
}
