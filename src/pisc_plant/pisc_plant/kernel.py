"""Compiled right-hand side and integrators of the plant (numba): a layout's entry points.

One kernel serves every scene: the state carries only the components a scene's
sub-models need (:class:`pisc_plant.layout.Layout`; the regularised Coulomb friction on
the cart is computed only in the layouts that model it), the constants travel in one
float array (:func:`pisc_plant.plant_config.pack_constants`), and the same compiled step
advances one rig in a node or ten thousand in a batch (:func:`for_layout` gives a
layout's entry points: one steps rows of a state array, the batch one hands chunks of
rows to it in parallel). Inside, the loop over rigs is vectorised, four rigs per AVX2
register, with sin, cos, pow and tanh from glibc's vector library
(:mod:`pisc_plant.vecmath`), and a rig gives bit-identical results alone and in a
batch. A plant set (every rig its own constants and step,
:func:`pisc_plant.plant_config.plant_set`) has entry points of its own that read each
rig's constants and operator table from blocks of :func:`pisc_plant.kernel_sets.lanes`;
a rig of a set gives the same bits as a plant of its own.

State order: ``x, x_dot, theta, theta_dot`` then, when modelled, the armature current
``i`` and the filtered sensor voltages ``v_ir, v_cur``. The input held over a step is
the applied armature voltage, or the cart force for an ideal force source.

Methods (:data:`pisc_plant.layout.METHODS`): ``rk4``, classical Runge-Kutta, and
``exprk4``, an exponential Runge-Kutta method of stiff order four, stable at any step
up to the period (:mod:`pisc_plant.kernel_steps` says how). README, "Scenes and
integrators", gives the measured order.

The kernel's modules, each compiled with the code of those it calls
(:mod:`pisc_plant.kernel_jit`: what that means for numba's cache):

* :mod:`pisc_plant.kernel_jit`: how each function is compiled; the kernel's files in
  the order their code is embedded;
* :mod:`pisc_plant.kernel_operators`: the exponential scheme's operators for a step;
* :mod:`pisc_plant.kernel_rhs`: the right-hand side and the end stops on one rig;
* :mod:`pisc_plant.kernel_steps`: one step of each method on one rig;
* :mod:`pisc_plant.kernel_batch`: the uniform entry points (rows, parallel chunks);
* :mod:`pisc_plant.kernel_sets`: the entry points of plant sets;
* this one: a layout's entry points (:func:`for_layout`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

from pisc_plant.kernel_batch import ENTRY_POINTS
from pisc_plant.kernel_sets import SET_POINTS
from pisc_plant.layout import Layout

__all__ = ["Kernels", "for_layout"]


class Kernels(NamedTuple):
    """The compiled functions of one layout (:func:`for_layout`)."""

    advance: Callable  # (ys, us, lo, hi, p, stops, method, substeps, h, coef): rows lo..hi
    advance_many: Callable  # (ys, us, p, stops, method, substeps, h, coef): all, in parallel
    # each rig its own constants p and operators (lanes layout) and step hs[k]:
    advance_set: Callable  # (ys, us, lo, hi, p, stops, method, substeps, hs, tables)
    advance_set_many: Callable  # (ys, us, p, stops, method, substeps, hs, tables)


def for_layout(layout: Layout) -> Kernels:
    """The kernels of a layout (each compiled on its first use, or loaded from cache;
    :func:`pisc_plant.warm.warm_up` compiles the uniform ones, not those of plant sets)."""
    return Kernels(*ENTRY_POINTS[(layout.armature, layout.filters, layout.coulomb)],
                   *SET_POINTS[(layout.armature, layout.filters)])
