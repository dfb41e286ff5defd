"""Calibration against the thesis's experiment: the batch it simulates is the robustness
batch's closed loop, the same seed gives the same posterior, the command writes a
distribution and a plant file that load and reproduce the experiment, and a joint block
of a distribution file is drawn row by row."""

from __future__ import annotations

import textwrap

import numpy as np
import pytest

from pisc_robust.calibrate import (
    calibrate,
    distance,
    experiment_config,
    experiment_prior,
    simulate_traces,
)
from pisc_robust.calibrate_cli import main as calibrate_main
from pisc_robust.experiment import judge, load_experiment, measure
from pisc_robust.robustness import prepare
from pisc_robust.uncertainty import load_distribution
from pisc_msgs_py.config import ConfigError
from pisc_plant.plant_config import plant_set
from pisc_sim.closed_loop import simulate_batch
from pisc_sim.configuration import load_graph_config, load_run_config


def test_the_traces_are_the_batch_closed_loop():
    """Four rigs of a plant set with noise and their own latencies: the hand-over and the
    lasting catch measured on the traces equal simulate_batch's own bookkeeping."""
    config, _ = load_graph_config("thesis")
    x0 = np.array([-0.13, -0.07, 0.08, 0.1])
    values = {"motor.rotor_inertia_kgm2": np.array([1e-6, 2e-6, 3e-6, 1e-6]),
              "noise.x_std_m": np.array([0.0, 4e-4, 2e-4, 1e-4]),
              "noise.theta_std_rad": np.array([1e-3, 0.0, 5e-4, 0.0])}
    delay = np.array([0.0, 0.001, 0.002, 0.0005])
    plant = plant_set(config.plant, values)
    duration = 3.0
    cycles = int(round(duration / config.loop.period_s)) + 1
    noise = np.random.default_rng(5).standard_normal((cycles, 4, 3))
    traces = simulate_traces(config, plant, x0, delay, cycles, noise)
    batch = simulate_batch(config, x0, duration, 2.0, delay, plant=plant, noise_seed=5)
    m = measure(traces)
    np.testing.assert_array_equal(m["hand_over_s"], batch.first_catch_s)
    catching = traces.mode[-1] == 1
    assert np.isfinite(batch.first_catch_s).sum() >= 2  # the comparison compares catches
    lasting = np.where(catching, batch.caught_at_s, np.inf)
    np.testing.assert_array_equal(np.isfinite(lasting), catching)


NARROW = """\
distribution:
  description: around one rig that reproduces the experiment
  parameters:
    motor.rotor_inertia_kgm2: {uniform: [0.95e-6, 1.05e-6]}
    noise.x_std_m: {uniform: [0.0, 1.0e-4]}
    initial.theta_rad: {offset: 0.5}
"""
EXPERIMENT = """\
experiment:
  configuration: thesis
  duration_s: 6.0
  start: {theta_rad: 3.141592653589793, theta_dot_radps: 0.0, x_dot_mps: 0.0,
          x_m: [-0.1315, -0.1285]}
  events:
    oscillations: {value: 3.0, tolerance: 0.5}
    hand_over_s: {value: 2.34, tolerance: 0.2}
    upright_s: {value: 3.25, tolerance: 0.3}
    catch_exits: {value: 0.0, tolerance: 0.5}
"""


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    where = tmp_path_factory.mktemp("calibration")
    (where / "narrow.yaml").write_text(NARROW)
    (where / "experiment.yaml").write_text(EXPERIMENT)
    return where


def small_run(files, seed, epsilons=(1.0,)):
    """Six particles a generation, proposed twelve at a time."""
    experiment = load_experiment(str(files / "experiment.yaml"))
    config, _ = load_graph_config("thesis")
    distribution = load_distribution(str(files / "narrow.yaml"), config)
    config, base = prepare(config, distribution)
    prior = experiment_prior(distribution, config, experiment)
    return calibrate(config, base, prior, experiment, 6, seed, epsilons, budget=120,
                     batch=12)


def test_the_prior_is_the_distribution_with_the_experiments_start(files):
    experiment = load_experiment(str(files / "experiment.yaml"))
    config, _ = load_graph_config("thesis")
    distribution = load_distribution(str(files / "narrow.yaml"), config)
    prior = experiment_prior(distribution, config, experiment)
    assert [r.name for r in prior.ranges] == ["initial.x_m", "motor.rotor_inertia_kgm2",
                                              "noise.x_std_m"]
    assert prior.range("initial.x_m").value_range == (-0.1315, -0.1285)
    assert experiment_config(config, experiment).initial.theta_dot_radps == 0.0


def test_the_same_seed_gives_the_same_posterior(files):
    first, again = small_run(files, 3, (2.0, 1.0)), small_run(files, 3, (2.0, 1.0))
    assert first.complete and [g.epsilon for g in first.generations] == [2.0, 1.0]
    for a, b in zip(first.generations, again.generations, strict=True):
        assert (a.simulated, a.accepted) == (b.simulated, b.accepted)
        for name in a.particles.values:
            np.testing.assert_array_equal(a.particles.values[name], b.particles.values[name])
        np.testing.assert_array_equal(a.weights, b.weights)
    assert [row[1:] for row in first.summary()] == [row[1:] for row in again.summary()]
    other = small_run(files, 4, (2.0, 1.0))
    assert not np.array_equal(first.posterior.values["initial.x_m"],
                              other.posterior.values["initial.x_m"])


def test_every_particle_meets_the_experiment_and_the_weights_are_importance_weights(files):
    """The last generation's particles all lie within the thesis's tolerances; the first
    generation (from the prior) weighs each alike, a later one by prior / kernel mixture,
    recomputed here from the previous generation (Beaumont et al. 2009)."""
    from scipy.stats import multivariate_normal

    from pisc_robust.calibrate import to_unit

    result = small_run(files, 3, (2.0, 1.0))
    experiment = result.experiment
    assert judge(experiment, result.final.measured).all()
    assert (distance(experiment, result.generations[0].measured) <= 2.0).all()
    np.testing.assert_allclose(result.generations[0].weights, 1 / 6)
    previous, final = result.generations
    before, after = (np.column_stack([to_unit(r, g.particles.values[r.name])
                                      for r in result.prior.ranges]) for g in (previous, final))
    cov = 2.0 * np.cov(before, rowvar=False, aweights=previous.weights)
    density = sum(w * multivariate_normal(u, cov, allow_singular=True).pdf(after)
                  for u, w in zip(before, previous.weights, strict=True))
    np.testing.assert_allclose(final.weights, (1 / density) / np.sum(1 / density),
                               rtol=1e-6)


def test_the_command_prints_the_posterior_and_writes_the_two_files(files, tmp_path, capsys):
    out = tmp_path / "out"
    status = calibrate_main(["--experiment", str(files / "experiment.yaml"), "--distribution",
                             str(files / "narrow.yaml"), "--particles", "6", "--epsilons",
                             "1", "--batch", "12", "--budget", "120", "--seed", "3",
                             "--noises", "2", "--workers", "0", "--out", str(out)])
    text = capsys.readouterr().out
    assert status == 0, text
    g = small_run(files, 3).final
    assert (f"generation at 1 x tolerance: {g.simulated} draws simulated, {g.accepted} within "
            f"it, acceptance rate {100 * g.accepted / g.simulated:.3f} %") in text
    assert "sample size 6, effective 6" in text
    assert "motor.rotor_inertia_kgm2" in text and "90 % interval" in text
    for name in ("posterior.png", "posterior.csv", "thesis-calibrated.yaml",
                 "thesis-calibrated-plant.yaml"):
        assert (out / name).stat().st_size > 0
    config, _ = load_graph_config("thesis")
    posterior = load_distribution(str(out / "thesis-calibrated.yaml"), config)
    assert posterior.rows is not None and len(posterior.rows) == 6
    draws = posterior.draw(50, 1)
    rows = {tuple(r) for r in posterior.rows.tolist()}
    joint = [r.name for r in posterior.ranges if r.kind == "joint"]
    assert joint == ["motor.rotor_inertia_kgm2", "noise.x_std_m"]  # not the cart's start
    for k in range(50):
        assert tuple(draws.values[n][k] for n in joint) in rows
    assert posterior.range("initial.theta_rad").kind == "offset"  # the prior's start
    run, _, plant = load_run_config("thesis", plant=str(out / "thesis-calibrated-plant.yaml"))
    assert -0.1315 <= plant["initial.x_m"] <= -0.1285
    assert 0.95e-6 <= run.simulated_plant.motor.rotor_inertia_kgm2 <= 1.05e-6
    assert "nominal plant: noise seed" in text


def test_bad_input_exits_2_naming_it(tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    bad.write_text(EXPERIMENT.replace("tolerance: 0.2", "tolerance: 0"))
    assert calibrate_main(["--experiment", str(bad), "--workers", "0"]) == 2
    assert "hand_over_s.tolerance = 0: must be above 0" in capsys.readouterr().err
    assert calibrate_main(["--distribution", "thesis-calibrated", "--workers", "0"]) == 2
    assert "thesis-calibrated: a distribution with a joint block cannot be the prior" in (
        capsys.readouterr().err)
    with pytest.raises(SystemExit):
        calibrate_main(["--epsilons", "1,2"])
    assert "decreasing, ending at 1" in capsys.readouterr().err


def write(tmp_path, text):
    path = tmp_path / "joint.yaml"
    path.write_text(textwrap.dedent(text))
    return path


JOINT = """\
distribution:
  plant:
    models: {friction: viscous}
  parameters:
    initial.x_m: {offset: 0.1}
  joint:
    names: [motor.resistance_ohm, friction.pivot_viscous_nms]
    rows:
    - [12.0, 1.0e-6]
    - [16.0, 3.0e-6]
"""


def test_a_joint_block_is_drawn_row_by_row(tmp_path):
    config, _ = load_graph_config("thesis")
    d = load_distribution(str(write(tmp_path, JOINT)), config)
    assert [(r.name, r.kind) for r in d.ranges] == [
        ("friction.pivot_viscous_nms", "joint"), ("initial.x_m", "offset"),
        ("motor.resistance_ohm", "joint")]
    assert d.range("motor.resistance_ohm").value_range == (12.0, 16.0)
    draws = d.draw(200, 9)
    pairs = set(zip(draws.values["motor.resistance_ohm"].tolist(),
                    draws.values["friction.pivot_viscous_nms"].tolist(), strict=True))
    assert pairs == {(12.0, 1e-6), (16.0, 3e-6)}
    np.testing.assert_array_equal(draws.values["initial.x_m"], d.draw(200, 9).values[
        "initial.x_m"])
    # the independent ranges draw as they would without the joint block
    alone = load_distribution(str(write(tmp_path, "distribution: {parameters: "
                                        "{initial.x_m: {offset: 0.1}}}")), config)
    np.testing.assert_array_equal(draws.values["initial.x_m"],
                                  alone.draw(200, 9).values["initial.x_m"])
    assert d.digest != alone.digest


@pytest.mark.parametrize(("old", "new", "says"), [
    ("names: [motor.resistance_ohm,", "names: [motor.nosuch_ohm,",
     ["distribution.joint.names", "motor.nosuch_ohm", "unknown parameter"]),
    ("- [16.0, 3.0e-6]", "- [16.0]", ["distribution.joint.rows[1]", "expected 2"]),
    ("- [16.0, 3.0e-6]", "- [-16.0, 3.0e-6]",
     ["distribution.joint.rows[1]", "motor.resistance_ohm = -16.0"]),
    ("initial.x_m: {offset: 0.1}", "motor.resistance_ohm: {relative: 0.1}",
     ["motor.resistance_ohm is both in distribution.joint"]),
    ("    rows:\n    - [12.0, 1.0e-6]\n    - [16.0, 3.0e-6]\n", "",
     ["distribution.joint", "names", "rows"]),
])
def test_a_bad_joint_block_is_refused_naming_it(tmp_path, old, new, says):
    assert old in JOINT
    with pytest.raises(ConfigError) as info:
        load_distribution(str(write(tmp_path, JOINT.replace(old, new))),
                          load_graph_config("thesis")[0])
    for word in says:
        assert word in str(info.value)


def test_the_shipped_calibrated_distribution_is_the_posterior_of_thesis_rig():
    """Its rows lie inside thesis-rig's ranges; it keeps thesis-rig's starts; pivot friction
    and R moved as the experiment says (docs/thesis-experiment.md)."""
    config, _ = load_graph_config("thesis")
    rig = load_distribution("thesis-rig", config)
    calibrated = load_distribution("thesis-calibrated", config)
    assert len(calibrated.rows) == 100
    for r in calibrated.ranges:
        prior = rig.range(r.name)
        if r.kind == "joint":
            lo, hi = prior.value_range
            assert lo - 1e-12 <= r.low <= r.high <= hi + 1e-12, r.name
        else:
            assert (r.kind, r.low, r.high) == (prior.kind, prior.low, prior.high)
    pivot = calibrated.rows[:, [r.name for r in calibrated.ranges if r.kind == "joint"].index(
        "friction.pivot_viscous_nms")]
    assert np.median(pivot) < 0.5 * rig.range("friction.pivot_viscous_nms").high / 2


def test_pisc_robustness_and_pisc_tune_take_the_calibrated_distribution(tmp_path, capsys):
    from pisc_robust.robustness_cli import main as robustness_main
    from pisc_robust.tune_cli import main as tune_main

    assert robustness_main(["thesis", "--distribution", "thesis-calibrated", "--draws", "20",
                            "--workers", "0", "--worst", "1", "--out",
                            str(tmp_path / "robustness")]) == 0
    out = capsys.readouterr().out
    assert "distribution thesis-calibrated" in out
    assert "motor.resistance_ohm in [" in out and "(joint rows)" in out
    tuned = tmp_path / "tuned.yaml"
    assert tune_main(["thesis", "--distribution", "thesis-calibrated", "--trials", "2",
                      "--draws", "10", "--workers", "0", "--out", str(tuned)]) == 0
    assert "# command: pisc_tune thesis --distribution thesis-calibrated" in tuned.read_text()
