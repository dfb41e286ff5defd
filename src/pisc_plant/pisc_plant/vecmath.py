"""sin, cos, pow and tanh for the compiled kernel, vectorisable across rigs.

numba compiles ``math.sin`` and its kin to calls of the C library's scalar functions,
and LLVM's loop vectoriser cannot widen those (the libm calls, 16-18 ns each, were a
third of the plant's time; README, "Batch"). glibc ships vector versions of them in
``libmvec`` (the x86-64 vector function ABI: ``_ZGVdN4v_sin`` takes and returns four
doubles in an AVX2 register). The intrinsics here compile to a call of a small
function, ``pisc_vm_<name>``, that carries LLVM's ``vector-function-abi-variant``
attribute naming its four-lane version, so that the vectoriser turns a loop over rigs
into calls of the four-lane function; the scalar function itself computes lane 0 of the
same four-lane call. Every rig therefore gets the same bits whether it is stepped alone,
in a vector body or in a loop's remainder: a rig alone and in a batch stay
bit-identical.

Without AVX2 or without ``libmvec`` (not glibc on x86-64), the functions are the C
library's scalar ones and nothing is vectorised; results then differ from a machine with
them in the last bits (glibc documents its vector functions to within 4 ulp). numba's
cache is keyed on the CPU, so the two kinds of code never mix in one cache. numba's
cache does not notice a change of this file, only of the kernel's own files: ``./pisc``
removes the kernel's entries when this file is newer (:mod:`pisc_plant.kernel_jit`).
"""

from __future__ import annotations

import ctypes
import ctypes.util

import llvmlite.binding as ll
import llvmlite.ir as lir
from numba.core import types
from numba.extending import intrinsic

__all__ = ["VECTOR_LIBRARY", "vcos", "vpow", "vsin", "vtanh"]

_ARITY = {"sin": 1, "cos": 1, "pow": 2, "tanh": 1}
_LANES = 4  # the AVX2 variants ("d" in the ABI's mangling): four doubles


def _vector_library() -> str | None:
    """The vector library's name if this machine can use it, else None."""
    features = ll.get_host_cpu_features()
    if not features.get("avx2", False):
        return None
    try:
        ll.load_library_permanently("libmvec.so.1")
    except RuntimeError:
        return None
    mvec = ctypes.CDLL("libmvec.so.1")
    if not all(hasattr(mvec, _vector_name(n)) for n in _ARITY):
        return None
    return "libmvec.so.1"


def _vector_name(name: str) -> str:
    return f"_ZGVdN{_LANES}{'v' * _ARITY[name]}_{name}"


VECTOR_LIBRARY = _vector_library()
if VECTOR_LIBRARY is None:
    _libm = ctypes.CDLL(ctypes.util.find_library("m"))
    for _name in _ARITY:
        ll.add_symbol(f"pisc_vm_{_name}",
                      ctypes.cast(getattr(_libm, _name), ctypes.c_void_p).value)


class _Attributes(lir.values.FunctionAttributes):
    """Function attributes with LLVM's string and memory attributes, which llvmlite's
    own set does not accept."""

    extra: tuple[str, ...] = ()

    def _to_list(self, ret_type):
        return super()._to_list(ret_type) + list(self.extra)


def _function(module: lir.Module, name: str) -> lir.Function:
    """``pisc_vm_<name>`` in ``module``: defined (lane 0 of the four-lane call, merged
    across modules) where the vector library is used, else declared (the C library's)."""
    scalar = f"pisc_vm_{name}"
    if scalar in module.globals:
        return module.globals[scalar]
    nargs = _ARITY[name]
    double = lir.DoubleType()
    fn = lir.Function(module, lir.FunctionType(double, [double] * nargs), scalar)
    if VECTOR_LIBRARY is None:
        return fn
    vec = lir.VectorType(double, _LANES)
    vname = _vector_name(name)
    vfn = module.globals.get(vname) or lir.Function(
        module, lir.FunctionType(vec, [vec] * nargs), vname)
    fn.linkage = "linkonce_odr"
    # not inlined: the vectoriser must see the scalar call it can widen
    attrs = _Attributes(("nounwind", "noinline"))
    attrs.extra = ("memory(none)", '"vector-function-abi-variant"='
                   f'"_ZGV_LLVM_N{_LANES}{"v" * nargs}_{scalar}({vname})"')
    fn.attributes = attrs
    builder = lir.IRBuilder(fn.append_basic_block())
    args = []
    for a in fn.args:
        # the argument in every lane: lanes left undefined could hold values that send
        # the vector function down its slow path for special inputs
        v = lir.Constant(vec, None)
        for lane in range(_LANES):
            v = builder.insert_element(v, a, lir.Constant(lir.IntType(32), lane))
        args.append(v)
    builder.ret(builder.extract_element(builder.call(vfn, args),
                                        lir.Constant(lir.IntType(32), 0)))
    return fn


def _codegen(name: str):
    def codegen(context, builder, signature, args):
        return builder.call(_function(builder.module, name), args)
    return codegen


@intrinsic
def vsin(typingctx, x):
    """sin(x) (see the module's docstring)."""
    return types.float64(types.float64), _codegen("sin")


@intrinsic
def vcos(typingctx, x):
    """cos(x)."""
    return types.float64(types.float64), _codegen("cos")


@intrinsic
def vtanh(typingctx, x):
    """tanh(x)."""
    return types.float64(types.float64), _codegen("tanh")


@intrinsic
def vpow(typingctx, x, y):
    """x ** y."""
    return types.float64(types.float64, types.float64), _codegen("pow")
