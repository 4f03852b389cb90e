"""The peer benchmark's mpipack side (tools/peers/mpipack_side.py): the ladder's fixed budgets
run all their iterations, also past the default scene's certified stop (the ladder passes
through the states of the shorter budgets; a budget that stopped early would hand it the same
state again and again, and the look-back of the finish line would never be met)."""

import os
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(os.path.dirname(HERE), "tools", "peers"))
import mpipack_side  # noqa: E402

START = {"n": 60, "dim": 2, "sigma": 0.5, "seed": 1}


def test_a_budget_runs_past_the_certified_stop(tmp_path):
    rc, summary, _, err = mpipack_side.run_mpipack(START, 1, str(tmp_path / "own"), None,
                                                   sets=["stop.max_iter=4000"], timeout=300)
    assert rc == 0 and summary["converged"], err
    certified_at = summary["iterations"]
    assert certified_at < 3000
    budget = certified_at + 500
    rc, summary, _, err = mpipack_side.run_mpipack(START, 1, str(tmp_path / "budget"), None,
                                                   sets=mpipack_side.budget_sets(budget), timeout=300)
    assert summary is not None, err
    assert summary["iterations"] == budget
