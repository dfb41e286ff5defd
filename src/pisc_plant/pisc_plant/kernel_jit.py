"""How the plant kernel is compiled (numba), and when its cache goes stale.

Every compiled function of the kernel is one of three kinds: :data:`compiled` (a
function numba compiles on its own), :data:`inlined` (a small helper inlined at numba's
IR level into its callers: as calls, passing their arrays cost more than their
arithmetic, measured 250 ns per operator application) and :data:`parallel` (a loop over
chunks of rigs shared between the cores, ``numba.prange``). All are cached on disk
(``cache=True``), next to their module in ``__pycache__``.

numba keys a module's cache entries on that module's file alone, but a compiled
function holds the code of everything it calls or inlines from other modules. So a
change to a module makes stale the entries of every module that calls into it:
:data:`SOURCES` lists the kernel's files so that each comes after every file whose code
it may hold, and ``./pisc`` removes, when one of them is newer than its last set-up, the
cache entries of that file and of every file after it (then compiles anew);
:mod:`pisc_gym.compiled`, whose pass holds the kernel's block step, removes its own
when any of them is newer. Code run otherwise after editing one of them needs
``src/pisc_plant/pisc_plant/__pycache__/kernel*`` deleted by hand.
"""

from __future__ import annotations

from pathlib import Path

import numba

__all__ = ["SOURCES", "compiled", "inlined", "parallel", "source_paths"]

#: The kernel's source files (in ``pisc_plant``), each after every file whose compiled
#: code it may hold (``./pisc`` lists the same, in the same order; test_warm checks both)
SOURCES = ("vecmath.py", "layout.py", "kernel_jit.py", "kernel_operators.py", "kernel_rhs.py",
           "kernel_steps.py", "kernel_batch.py", "kernel_sets.py")


def source_paths() -> list[Path]:
    """The paths of :data:`SOURCES`, for a cache that holds the kernel's code."""
    return [Path(__file__).with_name(name) for name in SOURCES]


compiled = numba.njit(cache=True, error_model="numpy")
inlined = numba.njit(cache=True, error_model="numpy", inline="always")
parallel = numba.njit(cache=True, parallel=True, error_model="numpy")
