"""tools/convergence_sweep.py keeps the figures of a run that outlasts the sweep's --timeout: the
run stops itself first (stop.max_seconds) and its row says so, exit 4 and the figures it
reached; a run that does not stop itself is killed and reported, the sweep goes on."""

import json
import os
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SWEEP = os.path.join(ROOT, "tools", "convergence_sweep.py")
sys.path.insert(0, os.path.join(ROOT, "tools"))

import convergence_sweep  # noqa: E402


def sweep(tmp_path, *extra, timeout=120):
    out = tmp_path / "rows.jsonl"
    proc = subprocess.run([sys.executable, SWEEP, "--n", "32000", "--seeds", "4", "--max-iter", "100000",
                           "--json", str(out), *extra],
                          capture_output=True, text=True, timeout=timeout, cwd=ROOT)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    rows = [json.loads(line) for line in out.read_text().splitlines()]
    assert len(rows) == 1, rows
    return proc, rows[0]


def test_loop_seconds_leave_room_under_the_timeout():
    for timeout in (6, 20, 600, 3600, 20000):
        limit = convergence_sweep.loop_seconds(timeout)
        assert 1.0 <= limit < timeout
    assert convergence_sweep.loop_seconds(20) == 10
    assert convergence_sweep.loop_seconds(3600) == 3480


def test_a_run_beyond_the_timeout_stops_itself_with_its_figures(tmp_path):
    # 2D N = 32000 seed 4 needs ~100000 iterations (minutes); 20 s leave it far from the end
    proc, row = sweep(tmp_path, "--timeout", "20")
    assert row["exit"] == 4 and row["converged"] is False, row
    assert row["stop_reason"] == "max_seconds", row
    assert row["iterations"] > 0 and row["W_over_N2"] > 0 and row["kkt"] > 0, row
    assert "0/1 certified" in proc.stdout


def test_a_run_that_does_not_stop_itself_is_reported_as_killed(tmp_path):
    proc, row = sweep(tmp_path, "--timeout", "4", "--set", "stop.max_seconds=600")
    assert row["exit"] == "timeout" and row["iterations"] is None, row
    assert "killed after the sweep's timeout of 4 s" in row["stderr"][0]
    assert "timeout" in proc.stdout
