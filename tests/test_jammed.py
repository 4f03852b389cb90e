"""stop.rule = "jammed": the quick finish (mpipack/stop/rule.py). It stops before the certificate
after the first iteration where the overlap is within stop.overlap and W has settled to
stop.jammed_rtol (whatever stop.check_every), exits 0 with a summary and a verdict that say
"jammed (not certified)" (the KKT residual reported, not required), on the same iteration and in
the same bits on 1, 2 and 3 ranks and across a restart; bad values of stop.jammed_rtol are
refused in one line (exit 2).
"""

import subprocess
import sys

import numpy as np
import pytest

import mpipack
from mpipack import config
from mpipack.stop.rule import JAMMED_MIN_WINDOW
from support import brute_force_figures

from conftest import assert_bitwise_equal, describe, mpi_env, mpipack_run

# the default scene's schedule (fire-al), small: certified at 1100 iterations, jammed at 1004
FIRE_AL = ["n=300"]
# the fixed DAHA of the paper's 3D scene, smaller: jammed at 3579 iterations; no certificate
# within 10000
FIXED = ("paper-3d", ["n=500", "stop.max_iter=10000"])


def run_rule(scene, sets, rule, **kw):
    return mpipack.run(scene, overrides=list(sets) + [f"stop.rule={rule}"], **kw)


def assert_jammed_summary(s, iterations=None):
    """What a jammed stop's summary says: the rule's exit 0, in words "jammed (not certified)"
    with the figures, converged false, the KKT residual reported (not required)."""
    assert s["exit_code"] == 0 and s["stop_reason"] == "jammed" and s["stop_rule"] == "jammed"
    assert s["converged"] is False
    assert s["exit_status"].startswith("jammed (not certified): max overlap ")
    assert "KKT residual" in s["exit_status"] and "W = " in s["exit_status"]
    j = s["jammed"]
    assert j["stopped_jammed"] and j["status"] == "jammed (not certified)" and not j["certified"]
    assert j["kkt_residual"] == s["kkt_residual"] and j["max_overlap"] == s["max_overlap"] and j["W"] == s["W"]
    test = j["test"]
    assert test["iteration"] == s["iterations"]
    assert test["w_change"] <= test["w_rtol"] == s["resolved_scene"]["stop"]["jammed_rtol"]
    assert test["window"] >= JAMMED_MIN_WINDOW
    assert test["kkt_required"] is False and test["kkt_residual"] == s["kkt_residual"]
    if iterations is not None:
        assert s["iterations"] == iterations


@pytest.mark.parametrize("scene,sets", [(None, FIRE_AL), FIXED], ids=["fire-al", "fixed-daha"])
def test_jammed_stops_before_the_certificate_with_a_packing(tmp_path, scene, sets):
    cert = run_rule(scene, sets, "certified")
    jam = run_rule(scene, sets, "jammed", out=str(tmp_path / "out"), gather=True)
    assert jam.exit_code == 0 and jam.stop_reason == "jammed" and not jam.converged, jam.error
    # earlier than the certificate, or where the certificate never came (exit 4 at the bound)
    assert cert.converged or cert.exit_code == 4
    assert jam.iterations < cert.iterations
    s = jam.summary
    assert_jammed_summary(s)
    assert s["certificate"]["overlap"]["ok"] and not s["certificate"]["kkt"]["ok"]
    # the packing itself, brute force on the gathered particles: no overlap beyond stop.overlap
    w, overlap = brute_force_figures(jam.particles)
    assert overlap <= s["resolved_scene"]["stop"]["overlap"]
    assert s["max_overlap"] == pytest.approx(overlap, rel=1e-9, abs=1e-15)
    assert s["W"] == pytest.approx(w, rel=1e-10)
    assert s["density"] is not None  # a packing: its density is reported


@pytest.mark.slow  # three mpiruns: about 40 s on this machine while others run
def test_same_stop_on_1_2_3_ranks_and_the_verdict_line(tmp_path):
    sets = FIRE_AL + ["stop.rule=jammed"]
    ref = None
    for ranks in (1, 2, 3):
        proc, s, d = mpipack_run(ranks, _mk(tmp_path / f"np{ranks}"), sets=sets, dump=True)
        assert proc.returncode == 0, describe(proc)
        assert_jammed_summary(s)
        # --quiet keeps the verdict's line alone: it says jammed, not certified, with the figures
        line = [ln for ln in proc.stdout.splitlines() if ln.startswith("mpipack: ")]
        assert len(line) == 1 and line[0].startswith("mpipack: jammed (not certified): max overlap "), describe(proc)
        assert "KKT residual" in line[0] and "W = " in line[0]
        if ref is None:
            ref = (s, d)
            continue
        assert s["iterations"] == ref[0]["iterations"]
        assert s["jammed"]["test"] == ref[0]["jammed"]["test"]
        assert_bitwise_equal(ref[1], d, f"jammed stop, {ranks} ranks against 1")


@pytest.mark.parametrize("cut", [900, 1002])
def test_a_restart_across_the_check_stops_on_the_same_iteration(tmp_path, cut):
    """Cut at an iteration that did not stop (900, in the 2D quench's stiff phase) and two
    before the stopping one (1002): the restarted run's W history and the schedule's quench
    come from the checkpoint and it stops where the straight run stops, in the same bits."""
    straight = run_rule(None, FIRE_AL, "jammed", gather=True)
    assert straight.stop_reason == "jammed" and cut < straight.iterations
    out = str(tmp_path / "out")
    first = run_rule(None, FIRE_AL + [f"stop.max_iter={cut}"], "jammed", out=out)
    assert first.exit_code == 4 and first.stop_reason == "max_iter" and first.iterations == cut
    again = mpipack.run(restart=out, overrides=["stop.max_iter=100000"], gather=True)
    assert again.exit_code == 0 and again.stop_reason == "jammed", again.error
    assert again.iterations == straight.iterations
    assert again.summary["jammed"]["test"] == straight.summary["jammed"]["test"]
    assert_bitwise_equal(straight.particles, again.particles, f"jammed stop, restart from {cut}")


# 3D: the jammed run quenches (``fire_al_schedule.QUENCH``): jammed at 719 iterations, certified
# at 5100
QUENCH_3D = ["dim=3", "n=300"]


def test_a_3d_jammed_run_quenches_long_before_the_certificate(tmp_path):
    cert = run_rule(None, QUENCH_3D, "certified")
    jam = run_rule(None, QUENCH_3D, "jammed", gather=True)
    assert cert.converged and jam.stop_reason == "jammed" and jam.exit_code == 0
    assert jam.iterations * 3 < cert.iterations, (jam.iterations, cert.iterations)
    assert_jammed_summary(jam.summary)
    w, overlap = brute_force_figures(jam.particles)
    assert overlap <= jam.summary["resolved_scene"]["stop"]["overlap"]
    assert jam.summary["W"] == pytest.approx(w, rel=1e-10)
    # a jammed packing, not the certified optimum: its W within a few per cent above
    assert cert.summary["W"] < jam.summary["W"] < 1.05 * cert.summary["W"]


@pytest.mark.parametrize("cut", [150, 550])
def test_a_3d_restart_across_the_quench_stops_on_the_same_iteration(tmp_path, cut):
    """Cut between the quench's window marks (150) and in its stiff phase (550): the mark and
    the schedule come from the checkpoint, the stop and the bits are the straight run's; and
    the same on 2 and 3 ranks."""
    straight = run_rule(None, QUENCH_3D, "jammed", gather=True)
    assert straight.stop_reason == "jammed" and cut < straight.iterations
    out = str(tmp_path / "out")
    first = run_rule(None, QUENCH_3D + [f"stop.max_iter={cut}"], "jammed", out=out)
    assert first.exit_code == 4 and first.iterations == cut
    again = mpipack.run(restart=out, overrides=["stop.max_iter=100000"], gather=True)
    assert again.exit_code == 0 and again.stop_reason == "jammed", again.error
    assert again.iterations == straight.iterations
    assert_bitwise_equal(straight.particles, again.particles, f"3D jammed stop, restart from {cut}")
    if cut == 550:
        for ranks in (2, 3):
            proc, s, d = mpipack_run(ranks, _mk(tmp_path / f"np{ranks}"), sets=QUENCH_3D + ["stop.rule=jammed"],
                                     dump=True)
            assert proc.returncode == 0, describe(proc)
            assert s["iterations"] == straight.iterations
            assert_bitwise_equal(straight.particles, d, f"3D jammed stop, {ranks} ranks against 1")


def test_the_jammed_stop_does_not_depend_on_the_certificate_checks():
    """The jammed test runs after every iteration on free figures: the same stop, in the same
    bits, whatever stop.check_every; and checks every few iterations do not stop the spread
    cloud at rest at the start (its W still for a few iterations: the window is at least
    JAMMED_MIN_WINDOW iterations)."""
    runs = {every: run_rule(None, QUENCH_3D + [f"stop.check_every={every}"], "jammed", gather=True)
            for every in (50, 7, 1)}
    ref = runs[50]
    assert ref.stop_reason == "jammed" and ref.iterations % 50 != 0  # between two checks
    for every, res in runs.items():
        assert res.stop_reason == "jammed" and res.iterations == ref.iterations, (every, res.iterations)
        assert res.summary["jammed"]["test"] == ref.summary["jammed"]["test"]
        assert_bitwise_equal(ref.particles, res.particles, f"jammed stop, check_every {every} against 50")
    # a packing: W within a few per cent of the certified one, not the cloud's
    cert = run_rule(None, QUENCH_3D, "certified")
    assert cert.converged and ref.summary["W"] < 1.05 * cert.summary["W"]


@pytest.mark.parametrize("value", ["0", "-1e-3", "1", "2.0", "nan", "inf", '"tight"', "true"])
def test_bad_jammed_rtol_is_refused_in_one_line(value):
    with pytest.raises(config.SceneError) as e:
        config.load(None, [f"stop.jammed_rtol={value}"])
    assert "stop.jammed_rtol" in str(e.value) and "\n" not in str(e.value)
    res = mpipack.run(None, overrides=[f"stop.jammed_rtol={value}"])
    assert res.exit_code == 2 and "stop.jammed_rtol" in res.error


def test_bad_jammed_rtol_exits_2_from_the_command_line(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "mpipack.cli", "run", "--set", "stop.rule=jammed",
                           "--set", "stop.jammed_rtol=0", "--out", str(tmp_path / "out")],
                          cwd=str(tmp_path), env=mpi_env(), capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2, describe(proc)
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("mpipack: error: key 'stop.jammed_rtol'"), describe(proc)


def test_the_rule_and_its_key_are_in_the_scene():
    scene = config.load(None, ["stop.rule=jammed"])
    assert scene.stop.rule == "jammed" and scene.stop.jammed_rtol == 1e-3
    assert config.load(None, ["stop.jammed_rtol=0.01"]).stop.jammed_rtol == 0.01


def _mk(path):
    path.mkdir(parents=True, exist_ok=True)
    return path
