"""Error measures recorded during a run (output.metrics_every -> metrics.csv): the paper's
N = 7 optimum is approached in every measure, and the rows are the same on 1, 2 and 3 ranks."""

import csv
from pathlib import Path

import numpy as np

from conftest import describe

N7 = ["n=7", "init.sigma=1.0", "method.alpha=0.35", "method.beta=1.4", "method.gamma=0.7",
      "stop.rule=eps", "stop.eps=1e-8", "output.metrics_every=20", "output.w_optimum=3"]


def rows(run_mpipack, P, sets):
    proc, summary, _ = run_mpipack(P, None, sets)
    assert proc.returncode == 0, describe(proc)
    out = Path(proc.args[proc.args.index("--out") + 1])
    with open(out / "metrics.csv") as f:
        return summary, list(csv.DictReader(f))


def test_metrics_rows_approach_the_optimum_and_are_rank_independent(run_mpipack):
    runs = {P: rows(run_mpipack, P, N7) for P in (1, 2, 3)}
    summary, r1 = runs[1]
    its = [int(r["iteration"]) for r in r1]
    assert its[:3] == [20, 40, 60] and its[-1] == summary["iterations"]
    last = r1[-1]
    assert abs(float(last["W_minus_optimum"])) < 1e-9
    assert float(last["kkt_residual"]) < 1e-5 and float(last["max_overlap"]) < 1e-6
    assert float(last["A"]) < 1e-10 and int(last["active_pairs"]) == 12  # the hexagon and its centre
    first = r1[0]
    for col in ("max_overlap", "A", "kkt_residual"):
        assert float(last[col]) < 1e-3 * float(first[col]), col
    assert float(last["W"]) == summary["W"]
    for P in (2, 3):
        _, rp = runs[P]
        assert len(rp) == len(r1)
        for a, b in zip(r1, rp):
            for col in a:
                if col != "wall_seconds":
                    assert a[col] == b[col], (P, col, a[col], b[col])
    assert np.isfinite([float(r["wall_seconds"]) for r in r1]).all()
