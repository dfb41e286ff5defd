"""pisc_tune: a search that improves a poor start, gives the same answer for the same
seed, resumes only its own study, and refuses a bad search space by name."""

from __future__ import annotations

import textwrap
from dataclasses import replace

import optuna
import pytest
import yaml

from pisc_sim.configuration import load_graph_config
from pisc_runs.verdict import Criteria
from pisc_robust.tune import StudyMismatch, Tuning, open_study, tune, tuned_file_text
from pisc_robust.tune_space import load_space, space_for
from pisc_robust.tune_cli import main as tune_main
from pisc_robust.uncertainty import load_distribution
from pisc_msgs_py.config import ConfigError

# caught by 3 s and held from 4.5 to 5 s (both tiers): less than half the simulated time
SHORT = Criteria(run_s=5.0, catch_by_s=3.0, hold_from_s=4.5, fast_by_s=3.0,
                 fast_hold_from_s=4.5)

# a rig near the nominal one with uneven starts
RIG = """\
distribution:
  plant: {noise: {x_std_m: 0.0004, theta_std_rad: 0.0015}}
  parameters:
    motor.resistance_ohm: {relative: 0.1}
    initial.theta_rad: {offset: 0.5}
    initial.theta_dot_radps: {offset: 1.0}
    initial.x_m: {offset: 0.1}
    initial.x_dot_mps: {offset: 0.2}
"""

# the thesis's law from the thesis's gains, with a pull towards the track's middle so
# strong that the cart leaves the safe range in about 4 of 10 draws (it catches some)
POOR = {"swing_up.k_x": 86.4, "swing_up.energy_target_j": 0.00094,
        "startup.distance_m": 0.069}
SPACE = """\
space:
  description: the swing-up's pull and energy target, and the start-up distance
  parameters:
    swing_up.k_x: {log: [1.0, 100.0]}
    swing_up.energy_target_j: {linear: [0.0, 0.003]}
    startup.distance_m: {linear: [0.0, 0.1]}
"""


def write(path, text: str):
    path.write_text(textwrap.dedent(text))
    return path


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("tune")
    return write(d / "rig.yaml", RIG), write(d / "space.yaml", SPACE)


def tuning(files, config="thesis", overrides=POOR, draws=100, seed=1, rig=None,
           sampler="tpe") -> Tuning:
    rig_path, space_path = files
    cfg, flat = load_graph_config(config, overrides)
    return Tuning(config, dict(overrides), load_distribution(str(rig or rig_path), cfg),
                  load_space(str(space_path), flat), draws, seed, sampler, SHORT)


@pytest.fixture(scope="module")
def first(files, tmp_path_factory):
    storage = f"sqlite:///{tmp_path_factory.mktemp('study') / 'a.db'}"
    t = tuning(files)
    return t, storage, tune(t, 12, storage)


def test_a_small_search_improves_a_poor_start(first):
    """Safe first: the search trades the unsafe start's catches for a configuration that
    keeps every draw in the safe range (the score counts catches only once safety meets
    its target)."""
    t, storage, result = first
    assert result.trials == 12
    assert 0.3 <= 1.0 - result.start_rates["safe"] <= 0.5  # the poor start
    assert result.start_rates["caught"] >= 0.1
    assert result.best_score > result.start_score
    tiers = ("safe", "caught", "fast")
    best = tuple(result.best_rates[t] for t in tiers)
    start = tuple(result.start_rates[t] for t in tiers)
    assert best > start  # better, safe first (tuples compare in order)
    assert result.best_rates["safe"] == 1.0
    assert result.best_trial > 0
    assert result.best_values["swing_up.k_x"] < 86.4
    assert result.best_flat["swing_up.k_x"] == result.best_values["swing_up.k_x"]
    assert result.best_flat["swing_up.k_v"] == 0.1  # the rest is the thesis's
    study = optuna.load_study(study_name=t.study_name, storage=storage)
    assert study.trials[0].user_attrs["start"] is True
    assert set(study.trials[0].user_attrs["rates"]) == {"safe", "caught", "fast", "hold_rms_a"}
    assert study.trials[0].params["swing_up.k_x"] == 86.4


def test_the_same_seed_gives_the_same_best(files, first, tmp_path):
    _, _, result = first
    again = tune(tuning(files), 12, f"sqlite:///{tmp_path / 'b.db'}")
    assert again.best_values == result.best_values
    assert again.best_score == result.best_score
    assert again.best_trial == result.best_trial


def test_the_same_command_resumes_its_study(files, first):
    t, storage, result = first
    again = tune(tuning(files), 12, storage)  # nothing left to do
    assert again == result
    more = tune(tuning(files), 13, storage)
    assert more.trials == 13 and more.best_score >= result.best_score


@pytest.mark.parametrize("change, named", [
    ({"rig": "other"}, "distribution_digest"),
    ({"draws": 50}, "draws 100 (now 50)"),
    ({"seed": 2}, "seed 1 (now 2)"),
    ({"overrides": {"swing_up.k_x": 3.0}}, "overrides"),
    ({"sampler": "cmaes"}, "sampler 'tpe' (now 'cmaes')"),
])
def test_a_study_of_another_tuning_is_refused_not_mixed_in(files, first, tmp_path, change,
                                                            named):
    _, storage, _ = first
    if change.get("rig") == "other":
        change = {"rig": write(tmp_path / "other.yaml",
                               RIG.replace("offset: 0.5", "offset: 0.4"))}
    before = len(optuna.get_all_study_summaries(storage))
    with pytest.raises(StudyMismatch, match="holds a tuning with another") as caught:
        open_study(tuning(files, **change), storage)
    assert named in str(caught.value)
    assert len(optuna.get_all_study_summaries(storage)) == before


def test_the_tuned_file_loads_and_says_where_it_comes_from(files, first, tmp_path):
    t, storage, result = first
    path = tmp_path / "tuned.yaml"
    path.write_text(tuned_file_text(result, t, "pisc_tune thesis ...", "2026-12-02", storage))
    head = [line for line in path.read_text().splitlines() if line.startswith("#")]
    text = "\n".join(head)
    for expected in ("command: pisc_tune thesis ...", "date: 2026-12-02",
                     f"distribution: rig (digest {t.distribution.digest})",
                     "draws 100, seed 1, sampler tpe, trials 12",
                     f"tiers on the same draws: start safe "
                     f"{100 * result.start_rates['safe']:.2f} %"):
        assert expected in text, expected
    config, flat = load_graph_config(str(path))
    assert config.supervisor.swing_up.k_x == result.best_values["swing_up.k_x"]
    assert config.supervisor.startup.distance_m == result.best_values["startup.distance_m"]
    assert flat["catch.poles"] == [-15.0, -11.0, -2.0, -1.5]


def test_a_candidate_the_configuration_refuses_scores_zero_and_is_marked(files, tmp_path):
    space = write(tmp_path / "space.yaml", """\
        space:
          parameters:
            switching.delta_exit: {linear: [0.05, 0.1]}   # below the thesis's delta_s 0.6
        """)
    t = tuning((files[0], space))
    storage = f"sqlite:///{tmp_path / 'r.db'}"
    with pytest.raises(ConfigError, match="the configuration refused all 3 candidates, the "
                       "last with: switching.delta_exit = .* must not be below"):
        tune(t, 3, storage)
    study = optuna.load_study(study_name=t.study_name, storage=storage)
    for trial in study.trials:
        assert trial.value == 0.0
        assert "switching.delta_exit" in trial.user_attrs["refused"]


def test_a_list_element_is_searched_alone(files, tmp_path):
    space = write(tmp_path / "space.yaml", """\
        space:
          parameters:
            catch.poles[3]: {linear: [-3.0, -1.0]}
        """)
    t = tuning((files[0], space), draws=20)
    result = tune(t, 2, f"sqlite:///{tmp_path / 'l.db'}")
    assert result.best_flat["catch.poles"][:3] == [-15.0, -11.0, -2.0]
    assert -3.0 <= result.best_flat["catch.poles"][3] <= -1.0


def test_a_start_outside_the_space_is_scored_apart(files, tmp_path):
    space = write(tmp_path / "space.yaml", """\
        space:
          parameters:
            swing_up.k_x: {log: [1.0, 10.0]}   # the start's k_x = 86.4 is outside
        """)
    t = tuning((files[0], space), draws=20)
    storage = f"sqlite:///{tmp_path / 'o.db'}"
    result = tune(t, 2, storage)
    study = optuna.load_study(study_name=t.study_name, storage=storage)
    assert all(1.0 <= trial.params["swing_up.k_x"] <= 10.0 for trial in study.trials)
    assert study.user_attrs["start_score"] == result.start_score


BAD_SPACES = {
    "nosuch.k_x": ("nosuch.k_x: {linear: [0, 1]}", "nosuch.k_x: cannot be searched"),
    "swing_up.k_nosuch": ("swing_up.k_nosuch: {linear: [0, 1]}",
                          "swing_up.k_nosuch: unknown parameter"),
    "the model": ("motor.resistance_ohm: {linear: [10, 20]}",
                  "motor.resistance_ohm: cannot be searched"),
    "the track": ("safety.x_max_m: {linear: [0.1, 0.2]}", "safety.x_max_m: cannot be searched"),
    "a whole list": ("catch.poles: {linear: [-5, -1]}",
                     "catch.poles: a list of 4 numbers; search one element, e.g. "
                     "catch.poles[0]"),
    "an index past the list": ("catch.poles[4]: {linear: [-5, -1]}",
                               "catch.poles[4]: index 4 beyond the 4 elements"),
    "an index of a number": ("swing_up.k_x[0]: {linear: [1, 2]}",
                             "swing_up.k_x[0]: swing_up.k_x is not a list"),
    "a string parameter": ("catch.design: {linear: [0, 1]}",
                           "catch.design: not a real number"),
    "low above high": ("swing_up.k_x: {linear: [10, 1]}",
                       "swing_up.k_x: linear: lower bound 10 must be below the upper bound 1"),
    "low equal to high": ("swing_up.k_x: {log: [2, 2]}",
                          "swing_up.k_x: log: lower bound 2 must be below the upper bound 2"),
    "log from zero": ("startup.distance_m: {log: [0, 0.1]}",
                      "startup.distance_m: log: [0, 0.1] must be positive"),
    "log of negative poles": ("catch.poles[2]: {log: [-5, -1]}",
                              "catch.poles[2]: log: [-5, -1] must be positive"),
    "a range that breaks the rule": ("swing_up.k_x: {linear: [-1, 10]}",
                                     "swing_up.k_x: the range reaches -1, which must be "
                                     "positive"),
    "an unknown scale": ("swing_up.k_x: {uniform: [1, 10]}",
                         "swing_up.k_x: expected one of linear, log"),
    "bounds not a pair": ("swing_up.k_x: {log: [1, 10, 100]}",
                          "swing_up.k_x: log: expected [low, high]"),
    "a malformed name": ("swing_up k_x: {log: [1, 10]}", "swing_up k_x: expected a parameter"),
}


@pytest.mark.parametrize("case", sorted(BAD_SPACES))
def test_a_bad_search_space_entry_is_refused_with_its_name(tmp_path, case):
    entry, message = BAD_SPACES[case]
    path = write(tmp_path / "space.yaml", f"space:\n  parameters:\n    {entry}\n")
    flat = load_graph_config("default")[1]
    with pytest.raises(ConfigError) as caught:
        load_space(str(path), flat)
    assert message in str(caught.value)
    assert str(caught.value).startswith(f"{path}: space.parameters.")


@pytest.mark.parametrize("text, message", [
    ("- swing_up.k_x", "one mapping under the key 'space'"),
    ("space: {parameters: {}}", "space.parameters must map parameter names to ranges"),
    ("space: {params: {swing_up.k_x: {log: [1, 10]}}}", "space.params: unknown key"),
])
def test_a_bad_search_space_file_is_refused(tmp_path, text, message):
    path = write(tmp_path / "space.yaml", text)
    with pytest.raises(ConfigError, match=message):
        load_space(str(path), load_graph_config("default")[1])


@pytest.mark.parametrize("config, space", [("default", "adaptive-space"),
                                           ("fixed-pump", "tuning-space"),
                                           ("thesis", "lyapunov-space"),
                                           ("lyapunov-tuned", "lyapunov-space")])
def test_each_shipped_configuration_has_its_space_and_refuses_the_others(config, space):
    """adaptive-space searches the adaptive default (the energy pump with the adaptation,
    the governor and the catch's guard), tuning-space the energy pump alone, lyapunov-space
    (3.30); a space whose parameters the configuration's law does not read is refused,
    naming the first such parameter and the setting that would read it."""
    flat = load_graph_config(config)[1]
    assert space_for(flat) == space
    names = [d.name for d in load_space(space, flat).dimensions]
    assert ("swing_up.pump_gain" in names) == (space != "lyapunov-space")
    assert ("swing_up.k_x" in names) == (space == "lyapunov-space")
    other = "tuning-space" if space == "lyapunov-space" else "lyapunov-space"
    with pytest.raises(ConfigError) as caught:
        load_space(other, flat)
    first, law = (("swing_up.k_x", "lyapunov") if other == "lyapunov-space"
                  else ("swing_up.pump_gain", "energy_pump"))
    assert f"space.parameters.{first}: not searched: the controllers read it only with " \
        f"swing_up.law: {law}; the configuration has swing_up.law: " in str(caught.value)
    assert f"e.g. {space})" in str(caught.value)


@pytest.mark.parametrize("entry, overrides, message", [
    ("swing_up.loss_gain: {linear: [0, 2]}", {"adaptation.enabled": False},
     "swing_up.loss_gain: not searched: the controllers read it only with swing_up.law: "
     "energy_pump and adaptation.enabled: true; the configuration has adaptation.enabled: "
     "false"),
    ("catch.governor_margin_m: {linear: [0, 0.05]}", {"catch.governor": False},
     "catch.governor_margin_m: not searched: the controllers read it only with "
     "catch.governor: true; the configuration has catch.governor: false"),
    ("catch.lqr_r: {log: [0.1, 10]}", {},
     "catch.lqr_r: not searched: the controllers read it only with catch.design: lqr"),
    ("catch.poles[1]: {linear: [-12, -2]}", {"catch.design": "lqr"},
     "catch.poles[1]: not searched: the controllers read it only with catch.design: poles"),
])
def test_a_parameter_the_configuration_does_not_read_is_refused(tmp_path, entry, overrides,
                                                                message):
    path = write(tmp_path / "space.yaml", f"space:\n  parameters:\n    {entry}\n")
    config = "fixed-pump"  # the energy pump, the adaptation, governor and guard off
    with pytest.raises(ConfigError) as caught:
        load_space(str(path), load_graph_config(config, overrides)[1])
    assert message in str(caught.value)
    # with the setting that reads it, the same entry is searched
    read = {"swing_up.loss_gain": {"adaptation.enabled": True},
            "catch.governor_margin_m": {"catch.governor": True},
            "catch.lqr_r": {"catch.design": "lqr"},
            "catch.poles[1]": {}}[entry.split(":")[0]]
    assert load_space(str(path), load_graph_config(config, read)[1]).dimensions


def test_pisc_tune_writes_the_file_and_refuses_a_study_of_another_distribution(
        files, tmp_path, capsys):
    rig, space = files
    out = tmp_path / "tuned.yaml"
    argv = ["thesis", "--distribution", str(rig), "--space", str(space), "--trials", "2",
            "--draws", "10", "--out", str(out)]
    assert tune_main(argv) == 0
    printed = capsys.readouterr().out
    assert "tiers on the same draws: start " in printed and f"wrote {out}" in printed
    assert (tmp_path / "tuned.db").exists()
    text = out.read_text()
    assert text.startswith("# pisc_tune: ")
    assert "# command: pisc_tune thesis --distribution" in text
    assert yaml.safe_load(text)["/**"]["ros__parameters"]["swing_up"]["k_v"] == 0.1
    other = write(tmp_path / "other.yaml", RIG.replace("offset: 0.5", "offset: 0.4"))
    argv[2] = str(other)
    assert tune_main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("pisc_tune: sqlite:///") and "distribution_digest" in err
    assert "Traceback" not in err


def exit_code(argv: list[str]) -> int:
    try:
        return tune_main(argv)
    except SystemExit as exc:  # argparse
        return int(exc.code)


@pytest.mark.parametrize("argv, message", [
    (["default", "--space", "nosuch"], "nosuch: no such search space"),
    (["thesis", "--set", "swing_up.k_e=100"], "(3.29)"),
    (["default", "--trials", "0"], "--trials 0: at least 1"),
    (["default", "--draws", "0"], "--draws 0: at least 1"),
    (["default", "--sampler", "nosuch"], "invalid choice: 'nosuch'"),
    (["default", "--storage", "nosuch://x"], "nosuch://x: cannot open the study storage"),
    (["default", "--scheduler", "notanaddress"],
     "--scheduler notanaddress: not a Dask scheduler's address (missing port number"),
    (["thesis", "--space", "tuning-space"], "swing_up.pump_gain: not searched"),
])
def test_pisc_tune_refuses_bad_arguments_with_exit_2(tmp_path, capsys, argv, message,
                                                     monkeypatch):
    import distributed

    def no_client(*args, **kwargs):  # a client made from a bad address hung for a minute
        raise AssertionError("a Dask client was made")

    monkeypatch.setattr(distributed, "Client", no_client)
    assert exit_code([*argv, "--out", str(tmp_path / "t.yaml")]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err
    assert not (tmp_path / "t.db").exists()


def test_ctrl_c_keeps_the_trials_says_how_many_and_the_same_study_resumes(files, tmp_path):
    """SIGINT (Ctrl-C) in the middle of a study: exit 130, one line that says how many
    trials the study keeps (no traceback); run again, the study goes on from them."""
    import signal
    import subprocess
    import sys
    import time

    rig, space = files
    storage = f"sqlite:///{tmp_path / 'tuned.db'}"

    def command(trials: int) -> list[str]:
        return [sys.executable, "-m", "pisc_robust.tune_cli", "thesis", "--set",
                "swing_up.k_x=2.0", "--distribution", str(rig), "--space", str(space),
                "--trials", str(trials), "--draws", "10", "--workers", "0", "--run-s", "5",
                "--catch-by", "3", "--hold-from", "4.5", "--fast-hold-from", "4.5",
                "--out", str(tmp_path / "tuned.yaml")]

    def complete() -> int:
        try:
            study = optuna.load_study(study_name=None, storage=storage)
        except (KeyError, ValueError):  # no study yet
            return 0
        return len(study.get_trials(states=(optuna.trial.TrialState.COMPLETE,)))

    child = subprocess.Popen(command(500), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                             text=True)
    try:
        while complete() < 2:
            assert child.poll() is None, child.communicate()
            time.sleep(0.2)
        child.send_signal(signal.SIGINT)
        _, err = child.communicate(timeout=300)
    finally:
        if child.poll() is None:
            child.kill()
    assert child.returncode == 130, err
    kept = complete()
    assert kept >= 2
    assert (f"pisc_tune: interrupted; {kept} trials kept in {storage}, rerun the same "
            "command to resume") in err
    assert "Traceback" not in err and "KeyboardInterrupt" not in err
    assert not (tmp_path / "tuned.yaml").exists()
    done = subprocess.run(command(kept + 1), capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    assert complete() == kept + 1


def test_aim_fast_puts_the_fast_draws_first_and_safe_second():
    """With --aim fast a candidate that never swings up (safe on every draw, caught on
    none) scores below one that is fast on 87 of 100 draws and safe on 88; with the
    default aim it is the other way round (one more safe draw outweighs any catch)."""
    import numpy as np

    from pisc_runs.verdict import Outcomes
    from pisc_robust.tune import score_for

    def outcomes(safe: int, caught: int, fast: int, n: int = 100) -> Outcomes:
        k = np.arange(n)
        arrays = [k < safe, k < caught, k < fast] + [np.zeros(n)] * 7 + [
            np.zeros(n, bool), k >= safe]
        return Outcomes(*arrays)

    idle, swinging = outcomes(100, 0, 0), outcomes(88, 88, 87)
    assert score_for("fast", swinging) > score_for("fast", idle)
    assert score_for("safe", swinging) < score_for("safe", idle)
    # fast first, then safe: one more fast draw outweighs every safe one
    assert score_for("fast", outcomes(87, 87, 87)) > score_for("fast", outcomes(100, 86, 86))
    assert score_for("fast", outcomes(100, 100, 100)) == 1.0
    assert score_for("fast", outcomes(90, 87, 87)) > score_for("fast", outcomes(88, 87, 87))


def test_the_aim_is_part_of_the_study_so_two_aims_never_mix(files, tmp_path):
    safe, fast = tuning(files, draws=5), replace(tuning(files, draws=5), aim="fast")
    assert "aim" not in safe.key() and fast.key()["aim"] == "fast"
    storage = f"sqlite:///{tmp_path / 'a.db'}"
    open_study(safe, storage)
    with pytest.raises(StudyMismatch, match="aim None \\(now 'fast'\\)"):
        open_study(fast, storage)
    with pytest.raises(ConfigError, match="aim 'slow': one of safe, fast"):
        replace(safe, aim="slow")
