"""The kernel's vectorisable sin, cos, pow and tanh (pisc_plant.vecmath)."""

import math

import numba
import numpy as np

from pisc_plant import vecmath
from pisc_plant.vecmath import vcos, vpow, vsin, vtanh


@numba.njit(error_model="numpy")
def _loop(a, b, e, out):
    for k in range(a.shape[0]):
        out[0, k] = vsin(a[k])
        out[1, k] = vcos(a[k])
        out[2, k] = vtanh(a[k])
        out[3, k] = vpow(b[k], e[k])


@numba.njit(error_model="numpy")
def _one(a, b, e):
    return vsin(a), vcos(a), vtanh(a), vpow(b, e)


def _inputs():
    rng = np.random.default_rng(7)
    a = np.concatenate([rng.uniform(-4.0, 4.0, 4000), rng.uniform(-3e3, 3e3, 997),
                        [0.0, -0.0, 1e-300, 1e5, -7.5e8]])
    b = np.concatenate([rng.uniform(1e-3, 30.0, 4997), [1.0, 2.0, 0.5, 3.0, 1e-3]])
    e = np.concatenate([rng.uniform(-4.0, 4.0, 4997), [0.0, -1.0, 0.5, -1.25, 2.0]])
    return a, b, e


def test_each_value_is_the_same_alone_and_in_a_loop_and_within_4_ulp_of_libm():
    """A rig's numbers must not depend on where in a batch it sits: the loop's vector
    body and remainder and a lone call give the same bits. Against the C library's
    scalar functions the values differ by at most 4 ulp (glibc's documented bound for
    its vector functions)."""
    a, b, e = _inputs()
    out = np.empty((4, a.size))
    _loop(a, b, e, out)
    for k in (0, 1, 2, 3, 4, 1234, a.size - 3, a.size - 2, a.size - 1):
        np.testing.assert_array_equal(out[:, k], _one(a[k], b[k], e[k]))
    reference = np.array([[math.sin(x) for x in a], [math.cos(x) for x in a],
                          [math.tanh(x) for x in a], [y ** x for x, y in zip(e, b, strict=True)]])
    ulps = np.abs(out - reference) / np.spacing(np.abs(reference))
    assert np.max(ulps) <= 4.0, np.max(ulps, axis=1)


def test_a_loop_over_rigs_calls_the_four_lane_functions_where_the_machine_has_them():
    """What makes the batch fast (README, "Batch"): with AVX2 and libmvec, LLVM widens
    the loop and calls the vector library's four-lane sin, cos, tanh and pow. Without
    them the loop calls the C library's scalar functions and nothing four-lane."""
    a, b, e = _inputs()
    _loop(a, b, e, np.empty((4, a.size)))
    ir = _loop.inspect_llvm(_loop.signatures[0])
    names = ("_ZGVdN4v_sin", "_ZGVdN4v_cos", "_ZGVdN4v_tanh", "_ZGVdN4vv_pow")
    if vecmath.VECTOR_LIBRARY is None:
        assert "_ZGV" not in ir
        assert "call double @pisc_vm_sin(" in ir
    else:
        for name in names:
            assert f"call <4 x double> @{name}(" in ir, name
