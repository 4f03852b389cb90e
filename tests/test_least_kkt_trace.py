"""tools/least_kkt_trace.py: the configuration's own KKT residual along a run (long fits),
the same figures on 1, 2 and 3 ranks."""

import json
import sys
from pathlib import Path

import pytest

from conftest import describe, mpirun

TOOL = Path(__file__).resolve().parents[1] / "tools" / "least_kkt_trace.py"
ARGS = ["--set", "n=300", "--start", "200", "--every", "200", "--last", "600",
        "--steps", "50,400"]


def rows_of(proc):
    return [json.loads(line) for line in proc.stdout.splitlines() if line.startswith("{")]


@pytest.fixture(scope="module")
def traces(tmp_path_factory):
    out = {}
    for P in (1, 2, 3):
        work = tmp_path_factory.mktemp(f"lkt{P}")
        proc = mpirun(P, [sys.executable, TOOL] + ARGS, cwd=work, timeout=300)
        assert proc.returncode == 0, describe(proc)
        out[P] = rows_of(proc)
    return out


def test_long_fits_bound_the_run_and_each_other(traces):
    rows = traces[1]
    assert [r["iteration"] for r in rows] == [200, 400, 600]
    for r in rows:
        # every fit starts at the run's multipliers and reports the least residual it met; the
        # 400-step fit repeats the 50-step one's first 50 steps
        assert r["fit400"] <= r["fit50"] <= r["run"]
        assert r["max_overlap"] >= 0 and r["W"] > 0
    assert any(r["fit400"] < 0.5 * r["run"] for r in rows), "the fits should find better multipliers"


def test_same_figures_on_1_2_3_ranks(traces):
    keys = ("iteration", "max_overlap", "W", "run", "fit50", "fit400")
    ref = [{k: r[k] for k in keys} for r in traces[1]]
    for P in (2, 3):
        assert [{k: r[k] for k in keys} for r in traces[P]] == ref, f"{P} ranks"


def test_bad_arguments_exit_with_one_line(tmp_path):
    proc = mpirun(1, [sys.executable, TOOL, "--every", "0", "--last", "10"], cwd=tmp_path,
                  timeout=120)
    assert proc.returncode != 0
    assert "least_kkt_trace: --every, --last and --steps must be positive" in proc.stderr
