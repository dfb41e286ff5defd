"""The seeds' analysis as a library: from a Lagrangian to gains, stability tests and maps.

Modules: :mod:`symbolic` (equations of motion from a Lagrangian, seed 001),
:mod:`linear` (equilibria, Jacobians, controllability, Ackermann / Bass-Gura, LQR),
:mod:`stability` (Krasovskii, Routh, the sampled PI current loop),
:mod:`comparisons` (seed 000's and seed 001's closed-loop simulations),
:mod:`roa` (regions of attraction of the catch in the sampled loop) and
:mod:`report` (the ``pisc_analysis`` command).
"""

__all__ = ["comparisons", "linear", "report", "roa", "stability", "symbolic"]
