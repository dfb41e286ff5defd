"""The pisc_analysis command: SPEC section 6 reproduced, the report's findings, the plots."""

import contextlib
import io
import re

import pytest

from pisc_analysis.report import spec_section6_checks
from pisc_analysis.report_cli import main

PUBLISHED = [-0.16302, 86.469, 2.1002, -18.210, -2.7711, -3.6696, -19.291, -2.0432,
             0.01235, 0.00867, 4.539, -4.539, 74.698, 16.587, 10.194, 9.1743]


def test_every_number_of_spec_section_6_is_reproduced():
    checks = spec_section6_checks()
    assert [c.published for c in checks] == PUBLISHED
    assert [c for c in checks if not c.ok] == []
    # (3.29) with Table 6.4: 0.01235 > 0.00867, as printed
    assert f"{checks[8].computed:.4g}" == "0.01235" and f"{checks[9].computed:.3g}" == "0.00867"


@pytest.fixture(scope="module")
def thesis_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("analysis")
    stdout, stderr = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
        status = main(["--config", "thesis", "--out", str(out), "--grid", "6",
                       "--roa-duration", "0.5", "--roa-x0", "0", "-0.1"])
    return status, stdout.getvalue(), stderr.getvalue(), out


def test_report_prints_the_spec_table_and_the_findings(thesis_run):
    status, text, _, _ = thesis_run
    assert status == 0
    assert "16 of 16 reproduced" in text
    for line in ("symbolic model equals SPEC section 2", "point mass (I = 0): symbolic model "
                 "equals SPEC section 2"):
        assert line in text
    assert "rank 4, determinant 1.05814e+07" in text
    assert "    gain the supervisor uses     K = [-2.771, -3.6695, -19.291, -2.0432]" in text
    assert "k_v / k_e = 0.012346 > 2 m g l a2 = 0.0086668: satisfied" in text
    assert "0 sign changes -> stable in continuous time" in text


def test_report_discrete_pi_unstable_at_6_ohm_stable_at_default(thesis_run):
    _, text, _, _ = thesis_run
    block = text.split("R = 6 ohm:")[1]
    assert re.search(r"quasi-static poles \[-1\.3432, 0\.35984\]  \|z\|max 1\.3432  UNSTABLE",
                     block)
    assert re.search(r"filter +poles .* stable", block.splitlines()[3])
    default = text.split("R = 14 ohm (configuration):")[1].split("R = 6 ohm")[0]
    assert default.count(" stable ") == 3 and "UNSTABLE" not in default
    assert "stable for R > 7.400 ohm (quasi-static)" in text
    assert "stable for R > 5.743 ohm (filter)" in text


def test_report_prints_seed_000_largest_difference_and_writes_the_plots(thesis_run):
    _, text, _, out = thesis_run
    assert "x          largest |nonlinear - linear| 0.2388 m at t = 0.476 s" in text
    names = sorted(p.name for p in out.iterdir())
    assert names == ["region_of_attraction.png", "seed000_linear_vs_nonlinear.png",
                     "seed001_linear_vs_nonlinear.png"]
    for p in out.iterdir():
        assert p.read_bytes()[:4] == b"\x89PNG"


def test_region_of_attraction_is_computed_for_both_gain_sets_without_a_bar_off_a_terminal(
        thesis_run):
    _, text, progress, _ = thesis_run
    for name in ("thesis", "default"):
        for x0 in ("+0.000", "-0.100"):
            assert f"    {name}: 6 x 6 starts at x0 = {x0} m, 0.50 s each" in text
    assert "thesis: criterion (4.1) k_va = 0.015 s^2, delta_s = 0.6 rad^2" in text
    # stderr is not a terminal: no bar of the steps or of the batch's cycles (they are
    # drawn on a terminal only: src/pisc_plant/test/test_progress.py)
    assert progress == ""


def test_an_unknown_configuration_is_refused_with_status_2(capsys):
    assert main(["--config", "no-such-rig", "--no-roa"]) == 2
    assert "pisc_analysis: invalid configuration: no-such-rig: no such configuration" in (
        capsys.readouterr().err)
