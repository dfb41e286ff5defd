"""``pisc_analysis``: the seeds' analysis of a configuration, as a printed report and plots.

    pisc_analysis [--config NAME|FILE] [--set NAME=VALUE ...] [--out DIR]
                  [--grid N] [--roa-duration S] [--roa-x0 X] [--compare NAME ...]
                  [--no-roa]

Prints, for the configuration's rig and controller: the symbolic model checked
against SPEC section 2, the equilibria, A and B about upright, the open-loop poles,
controllability, the catch gain by three pole placements (and LQR), condition (3.29),
Routh's table of the continuous PI loop (3.51), the sampled PI loop's poles,
Krasovskii's test; then every number of SPEC section 6 against its published value,
seed 000's and seed 001's linear vs nonlinear comparisons, and the region of
attraction of the catch for the configuration and the ones it is compared with.
Writes the plots as PNG into ``--out``. Exit status 0, or 2 when the configuration is
refused.
"""

from __future__ import annotations

import io
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, TextIO

import numpy as np
import sympy as sp

from pisc_analysis import comparisons, linear, roa, stability, symbolic
from pisc_sim.configuration import GraphConfig, load_graph_config
from pisc_control.catch import catch_gain
from pisc_control.swing_up import SwingUpParams, gain_condition
from pisc_msgs_py.progress import progress_bar
from pisc_model.dynamics import linearise_upright
from pisc_model.params import RigParams

__all__ = ["Report", "SpecCheck", "build_report", "spec_section6_checks"]

THESIS_POLES = (-15.0, -11.0, -2.0, -1.5)
SPEC_RTOL = 5e-5  # the published values' fifth significant digit


@dataclass(frozen=True)
class SpecCheck:
    """One published number of SPEC section 6 against the value computed here."""

    source: str
    quantity: str
    published: float
    computed: float
    rtol: float = SPEC_RTOL

    @property
    def ok(self) -> bool:
        return abs(self.computed - self.published) <= self.rtol * abs(self.published)

    def line(self) -> str:
        rel = abs(self.computed - self.published) / abs(self.published)
        return (f"{self.source:<16} {self.quantity:<34} {self.published:>11.6g} "
                f"{self.computed:>13.7g} {rel:>9.1e}  {'ok' if self.ok else 'DIFFERS'}")


@dataclass
class Report:
    lines: list[str] = field(default_factory=list)
    plots: list[Path] = field(default_factory=list)
    checks: list[SpecCheck] = field(default_factory=list)

    def add(self, *lines: str) -> None:
        self.lines.extend(lines)

    def section(self, title: str) -> None:
        self.lines.extend(["", title, "-" * len(title)])

    @property
    def text(self) -> str:
        return "\n".join(self.lines)


def _matrix(a: np.ndarray, indent: str = "    ") -> list[str]:
    text = np.array2string(np.asarray(a), precision=5, suppress_small=True, max_line_width=110)
    return [indent + line for line in text.splitlines()]


def _rig_values(s: symbolic.CartPoleSymbols, rig: RigParams) -> dict[sp.Symbol, float]:
    return {s.M: rig.cart_mass_kg, s.m: rig.pendulum_mass_kg, s.l: rig.pendulum_com_m,
            s.I: rig.pendulum_inertia_kgm2, s.g: rig.gravity_mps2}


def spec_section6_checks() -> list[SpecCheck]:
    """Every number of SPEC section 6, computed by this package's own functions."""
    system, s = symbolic.cart_pole(with_inertia=True)
    rig = RigParams()  # thesis Table 6.1
    a, b = linear.linearise(system, _rig_values(s, rig))
    k = linear.bass_gura_gain(a, b, THESIS_POLES)
    ratio, bound = gain_condition(rig, SwingUpParams())  # Table 6.4: k_v 0.1, k_e 8.1
    point, sp_ = symbolic.cart_pole(with_inertia=False)
    seed_rig = comparisons.SEED001_RIG
    a1, b1 = linear.linearise(point, _rig_values(sp_, seed_rig))
    poles = np.sort(np.linalg.eigvals(a1).real)
    f = -linear.bass_gura_gain(a1, b1, comparisons.SEED001_POLES)
    checks = [
        SpecCheck("thesis (6.3)", "-a1 g/(a2-a1) = A[1,2]", -0.16302, a[1, 2]),
        SpecCheck("thesis (6.3)", "a1 a2 g/(m l (a2-a1)) = A[3,2]", 86.469, a[3, 2]),
        SpecCheck("thesis (6.3)", "1/(a2-a1) = B[1]", 2.1002, b[1, 0]),
        SpecCheck("thesis (6.3)", "-a1/(m l (a2-a1)) = B[3]", -18.210, b[3, 0]),
    ]
    for i, published in enumerate((-2.7711, -3.6696, -19.291, -2.0432)):
        checks.append(SpecCheck("thesis Table 6.3", f"K{i + 1} (poles -15,-11,-2,-1.5)",
                                published, k[i]))
    checks += [
        SpecCheck("thesis (3.29)", "k_v / k_e (Table 6.4)", 0.01235, ratio, 5e-4),
        SpecCheck("thesis (3.29)", "2 m g l a2", 0.00867, bound, 5e-4),
        SpecCheck("seed 001", "open-loop pole +", 4.539, poles[-1], 1e-4),
        SpecCheck("seed 001", "open-loop pole -", -4.539, poles[0], 1e-4),
    ]
    for name, published, value in (("theta", 74.698, f[2]), ("theta_dot", 16.587, f[3]),
                                   ("x", 10.194, f[0]), ("x_dot", 9.1743, f[1])):
        checks.append(SpecCheck("seed 001", f"F coefficient of {name}", published, value))
    return checks


def _model_section(report: Report, config: GraphConfig) -> tuple[Any, Any, dict]:
    rig = config.supervisor.rig
    report.section("1. Equations of motion from the Lagrangian (seed 001 dyn1-dyn4)")
    results = []
    for with_inertia in (True, False):
        system, s = symbolic.cart_pole(with_inertia=with_inertia)
        acc = system.accelerations()
        hand = symbolic.cart_pole_hand_accelerations(s, system.q[1], system.dq[1],
                                                     with_inertia)
        same = all(sp.simplify(a - h) == 0 for a, h in zip(acc, hand, strict=True))
        results.append(same)
        verdict = ("equals SPEC section 2 (the difference simplifies to 0)" if same
                   else "DIFFERS FROM SPEC section 2")
        report.add(f"cart-pole {'with I' if with_inertia else 'point mass (I = 0)'}: "
                   f"symbolic model {verdict}")
    system, s = symbolic.cart_pole(with_inertia=True)
    values = _rig_values(s, rig)
    report.add("mass matrix M = dr/dq'' (seed 001 (9)):", *[
        "    " + str(row) for row in system.mass_matrix().tolist()])
    report.add("stiffness K = dr/dq (7):", *["    " + str(row)
                                              for row in system.stiffness_matrix().tolist()])
    report.add("damping C = dr/dq' (8):", *["    " + str(row)
                                            for row in system.damping_matrix().tolist()])
    report.add("state space z = [x, x_dot, theta, theta_dot]:")
    for name, expr in zip(("x_dot", "x_ddot", "theta_dot", "theta_ddot"),
                          system.state_space(), strict=True):
        report.add(f"    {name} = {expr}")
    return system, s, values


def _linear_section(report: Report, config: GraphConfig, system: Any, s: Any,
                    values: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rig = config.supervisor.rig
    report.section("2. Equilibria and linearisation (seed 000 sections 5-6, thesis (3.41)-(3.42))")
    eq = linear.equilibria(system, values)
    angles = ", ".join(f"theta = {float(sol[system.q[1]]):.6g}" for sol in eq.solutions)
    report.add(f"equilibria with f = 0: {angles}; velocities 0; free: "
               f"{', '.join(map(str, eq.free))} (any value) (3.13)-(3.15)")
    none = linear.equilibria(system, values, {s.f: 0.1})
    report.add(f"with a constant f = 0.1 N: {len(none.solutions)} equilibria (seed 000 solved "
               "its two equations one at a time and reported spurious angles)")
    a, b = linear.linearise(system, values)
    a_hand, b_hand = linearise_upright(rig)
    report.add("A about upright:", *_matrix(a), "B:", *_matrix(b.T))
    report.add(f"largest difference from the hand-derived (3.41)-(3.42): "
               f"{max(np.max(np.abs(a - a_hand)), np.max(np.abs(b - b_hand))):.2e}")
    a_down, b_down = linear.linearise(system, values, state=[0.0, 0.0, math.pi, 0.0])
    report.add("A, B hanging (theta = pi):", *_matrix(a_down), *_matrix(b_down.T))
    poles = np.sort_complex(np.linalg.eigvals(a))
    report.add(f"open-loop poles upright: {_complex_list(poles)} 1/s; hanging: "
               f"{_complex_list(np.sort_complex(np.linalg.eigvals(a_down)))} 1/s")
    c = linear.controllability(a, b)
    expected = rig.gravity_mps2**2 * rig.a1**4 / (rig.ml**4 * (rig.a1 - rig.a2) ** 4)
    report.add("controllability matrix [B AB A^2B A^3B]:", *_matrix(c.matrix),
               f"rank {c.rank}, determinant {c.determinant:.6g} (thesis (3.45): "
               f"g^2 a1^4 / (m^4 l^4 (a1 - a2)^4) = {expected:.6g})")

    report.section("3. Catch gain (seed 001 (22)-(25), Ackermann, python-control, LQR)")
    report.add(f"open-loop characteristic coefficients a1..a4 (seed 001 (21)): "
               f"{_real_list(linear.characteristic_coefficients(a))}")
    cat = config.supervisor.catch
    k_config = catch_gain(rig, cat)
    if cat.design == "poles":
        poles_cfg = cat.pole_set
        report.add(f"configuration: design 'poles' at {_complex_list(poles_cfg)}")
        for name, fn in (("Bass-Gura (23)-(25)", linear.bass_gura_gain),
                         ("Ackermann", linear.ackermann_gain),
                         ("python-control place/acker", linear.place_gain)):
            report.add(f"    {name:<28} K = {_real_list(fn(a, b, poles_cfg))}")
    else:
        report.add(f"configuration: design 'lqr', Q = diag{list(cat.lqr_q)}, R = {cat.lqr_r}")
    report.add(f"    gain the supervisor uses     K = {_real_list(k_config)}")
    report.add(f"    closed-loop poles {_complex_list(linear.closed_loop_poles(a, b, k_config))}")
    k_lqr = linear.lqr_gain(a, b, np.diag(cat.lqr_q), cat.lqr_r)
    report.add(f"LQR alternative (Q = diag{list(cat.lqr_q)}, R = {cat.lqr_r}): "
               f"K = {_real_list(k_lqr)}, poles "
               f"{_complex_list(linear.closed_loop_poles(a, b, k_lqr))}")
    report.add(f"f = -K z; the C++ program's positive k's are -K: "
               f"{_real_list(-k_config)}")
    return a, b, k_config


def _stability_section(report: Report, config: GraphConfig, system: Any, values: dict,
                       a: np.ndarray, b: np.ndarray, k: np.ndarray) -> None:
    rig = config.supervisor.rig
    su = config.supervisor.swing_up
    report.section("4. Swing-up gain condition (3.29)")
    ratio, bound = gain_condition(rig, su)
    what = "2 m g l a2" if su.energy_target_j == 0.0 else "a2 (2 m g l + E_ref)"
    report.add(f"k_v / k_e = {ratio:.5g} {'>' if ratio > bound else '<='} {what} = "
               f"{bound:.5g}: {'satisfied' if ratio > bound else 'VIOLATED'}")

    motor, loop, period = config.plant.motor, config.current_loop, config.loop.period_s
    report.section("5. PI current loop: Routh (3.51), thesis Table 3.1")
    for label, inertia in (("rotor alone (J_m, as the thesis)", None),
                           ("rotor with the cart (J_m + (M+m) r^2)",
                            motor.rotor_inertia_kgm2 + rig.a2 * motor.wheel_radius_m**2)):
        coeffs = stability.pi_characteristic_polynomial(motor, loop, inertia)
        table, changes = stability.routh_table(coeffs)
        report.add(f"{label}: c3..c0 = {_real_list(coeffs)}",
                   f"    first column {_real_list(table[:, 0])}: {changes} sign changes -> "
                   f"{'stable' if changes == 0 else 'UNSTABLE'} in continuous time "
                   "(for every positive k_pi, k_ii, (3.60))")

    report.section("6. PI current loop as it runs: sampled at Ts with a zero-order hold")
    report.add(f"k_pi = {loop.k_pi} V/A, k_ii = {loop.k_ii} V/(A s), Ts = {period * 1e3:g} ms, "
               f"L = {motor.inductance_h * 1e3:g} mH, current sensor filter "
               f"{config.plant.sensors.current_filter_hz:g} Hz")
    filt = config.plant.sensors.current_filter_hz
    models = (("quasi-static", "R z^2 + (k_pi + k_ii Ts - R) z - k_pi (SPEC section 3)"),
              ("armature", "exact ZOH armature, current measured directly"),
              ("filter", f"exact ZOH armature behind the {filt:g} Hz RC filter (the rig)"))
    for r in sorted({motor.resistance_ohm, 6.0}, reverse=True):
        report.add(f"R = {r:g} ohm{' (configuration)' if r == motor.resistance_ohm else ''}:")
        for model, text in models:
            chk = stability.sampled_pi_check(replace(motor, resistance_ohm=r), loop, period,
                                             model=model, sensor_filter_hz=filt)
            report.add(f"    {model:<12} poles {_complex_list(chk.poles)}  |z|max "
                       f"{chk.spectral_radius:.4f}  {'stable' if chk.stable else 'UNSTABLE'}"
                       f"   [{text}]")
    for model, _unused in models:
        limit = stability.sampled_pi_resistance_limit(motor, loop, period, model=model,
                                                      sensor_filter_hz=filt)
        report.add(f"stable for R > {limit:.3f} ohm ({model})")
    report.add("Without the sensor filter the thesis gains are unstable at 6 ohm (a pole near "
               "z = -1.34: the loop rings at the Nyquist frequency and saturates); the 72 Hz "
               "filter attenuates that frequency and moves the boundary below 6 ohm. Routh's "
               "continuous test sees neither.")

    report.section("7. Krasovskii's test on the catch loop (seed 001 section 3)")
    jac = stability.closed_loop_jacobian(system, values, k)
    plain = stability.krasovskii(jac, np.zeros((1, 4)))
    verdict = "negative definite" if plain.negative_definite else "NOT negative definite"
    report.add(f"P = I (seed 001's form): largest eigenvalue of A + A^T at the origin "
               f"{plain.max_eigenvalue:.4g} -> {verdict}; F[0,0] = 2 d(x_dot)/dx = 0 for any "
               "[q, q'] model, so this form cannot pass")
    a_cl = a - b @ k.reshape(1, 4)
    p = stability.lyapunov_matrix(a_cl)
    scale = (0.1, 0.5, 0.1, 1.0)
    radius = stability.krasovskii_radius(jac, p, scale)
    report.add(f"P from A_cl^T P + P A_cl = -I (generalised Krasovskii): negative definite at "
               f"the origin; on 4000 sampled states with |z / s| <= r, "
               f"s = (x {scale[0]} m, x_dot {scale[1]} m/s, theta {scale[2]} rad, theta_dot "
               f"{scale[3]} rad/s): r = {radius:.3f} (theta up to {radius * scale[2]:.3f} rad)")


def _complex_list(values: Sequence[complex]) -> str:
    out = []
    for v in values:
        v = complex(v)
        out.append(f"{v.real:.5g}" if abs(v.imag) < 1e-9 else
                   f"{v.real:.5g}{v.imag:+.5g}j")
    return "[" + ", ".join(out) + "]"


def _real_list(values: Sequence[float]) -> str:
    return "[" + ", ".join(f"{float(v):.5g}" for v in values) + "]"


def build_report(
    config_name: str,
    overrides: dict[str, Any] | None = None,
    out_dir: Path | None = None,
    grid: int = 100,
    roa_duration_s: float = 1.5,
    roa_x0_m: Sequence[float] = (0.0,),
    compare: Sequence[str] = (),
    progress: TextIO | None = None,
) -> Report:
    """The whole report; plots go to ``out_dir`` (none when None); ``grid = 0`` skips the
    region of attraction. ``progress`` (stderr for the command) shows a bar of the steps,
    and one of each region of attraction's cycles, when it is a terminal."""
    maps = (1 + len(compare)) * len(roa_x0_m) if grid > 0 else 0
    stream = progress or io.StringIO()
    with progress_bar(3 + maps, "step", "pisc_analysis", stream=stream) as steps:
        return _build_report(config_name, overrides, out_dir, grid, roa_duration_s, roa_x0_m,
                             compare, stream, steps)


def _build_report(config_name: str, overrides: dict[str, Any] | None, out_dir: Path | None,
                  grid: int, roa_duration_s: float, roa_x0_m: Sequence[float],
                  compare: Sequence[str], stream: TextIO, steps: progress_bar) -> Report:
    started = time.perf_counter()
    config, _ = load_graph_config(config_name, overrides)
    report = Report()
    report.add(f"PISC analysis of configuration '{config_name}'"
               + (f" with {overrides}" if overrides else ""))
    rig = config.supervisor.rig
    report.add(f"rig: M = {rig.cart_mass_kg} kg, m = {rig.pendulum_mass_kg} kg, "
               f"l = {rig.pendulum_com_m} m, I = {rig.pendulum_inertia_kgm2} kg m^2, "
               f"g = {rig.gravity_mps2} m/s^2; a1 = {rig.a1:.6g} kg, a2 = {rig.a2:.6g} kg")
    steps.describe("equations of motion (sympy)")
    system, s, values = _model_section(report, config)
    a, b, k = _linear_section(report, config, system, s, values)
    steps(1)
    steps.describe("stability tests")
    _stability_section(report, config, system, values, a, b, k)

    report.section("8. SPEC section 6: published numbers, computed here")
    report.add(f"{'source':<16} {'quantity':<34} {'published':>11} {'computed':>13} "
               f"{'rel.diff':>9}")
    report.checks = spec_section6_checks()
    report.add(*(c.line() for c in report.checks))
    good = sum(c.ok for c in report.checks)
    report.add(f"{good} of {len(report.checks)} reproduced: five-digit values within a "
               "relative 5e-5 (at most about one unit of the last printed digit: Table 6.3's "
               "K2 -3.6696 is -3.66946 here), (3.29) and the seed 001 poles to their printed "
               "digits")

    steps(1)
    steps.describe("seed comparisons")
    report.section("9. Linear vs nonlinear closed loops (seed 000 section 7, seed 001 section 5)")
    for name, comparison in (("seed000", comparisons.seed000_comparison()),
                             ("seed001", comparisons.seed001_comparison())):
        report.add(comparison.title, *["    " + line for line in comparison.summary_lines()])
        if out_dir is not None:
            report.plots.append(comparisons.plot_comparison(
                comparison, Path(out_dir) / f"{name}_linear_vs_nonlinear.png"))
    report.add("Seed 000's result holds: the responses are close and differ most in the "
               "transient (largest x difference in the first second), not in steady state.")
    steps(1)

    if grid > 0:
        report.section("10. Region of attraction of the catch (sampled, quantised, saturated "
                       "loop, switching rule (4.1))")
        theta = np.linspace(-1.0, 1.0, grid)
        rate = np.linspace(-8.0, 8.0, grid)
        maps = []
        for name in (config_name, *compare):
            cfg = config if name == config_name else load_graph_config(name)[0]
            sw = cfg.supervisor.switching
            report.add(f"{name}: criterion (4.1) k_va = {sw.k_va} s^2, delta_s = "
                       f"{sw.delta_s} rad^2; catch poles "
                       f"{_complex_list(cfg.supervisor.catch.pole_set)}")
            for x0 in roa_x0_m:
                what = f"region of attraction '{name}' x0 = {x0:+g} m"
                steps.describe(what)
                # and a bar of the batch's cycles below the steps'
                with progress_bar(0, "cycle", "cycles", stream=stream) as bar:
                    maps.append(roa.region_of_attraction(
                        cfg, theta, rate, x0_m=x0, duration_s=roa_duration_s, label=name,
                        progress=lambda k, n: bar.to(k, n)))
                steps(1)
                report.add("    " + maps[-1].summary())
        report.add("Caught at once: in catch from the first sample and |theta| < 0.05 rad over "
                   "the last 0.5 s without a fault; caught later: by the swing-up and the "
                   "switching rule within the same time. The catch holds a band of starts "
                   "moving towards upright; starts inside (4.1) moving away are lost, the "
                   "pendulum falling while the 0.9 A current limit saturates the force, or "
                   "the cart leaving the safe range on the short track.")
        if out_dir is not None:
            report.plots.append(roa.plot_roa(maps, Path(out_dir) / "region_of_attraction.png",
                                             columns=len(roa_x0_m)))

    if report.plots:
        report.section("Plots")
        report.add(*(str(p) for p in report.plots))
    report.add("", f"analysis took {time.perf_counter() - started:.1f} s")
    return report
