"""The peer benchmark's mpipack side (tools/peers/mpipack_side.py): the ladder's fixed budgets
run all their iterations, also past the default scene's certified stop (the ladder passes
through the states of the shorter budgets; a budget that stopped early would hand it the same
state again and again, and the look-back of the finish line would never be met)."""

import os
import sys

import pytest

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


def ladder_args(chain, n0=200, max_iter=1500):
    import argparse
    return argparse.Namespace(ratio=1.5 ** (1.0 / 3.0), n0=n0, max_iter=max_iter, ladder_wall_limit=None,
                              time_limit=None, run_timeout=300, verbose=False, chain=chain,
                              overlap_tol=1e-3, w_tol=5e-3, lookback=1.0 / 3.0, window=3)


@pytest.fixture(scope="module")
def plain_ladder(tmp_path_factory):
    return mpipack_side.ladder(START, 1, ladder_args(False), str(tmp_path_factory.mktemp("plain")))


@pytest.mark.parametrize("ranks", [1, 3])
def test_a_chained_ladder_passes_through_the_same_states(plain_ladder, ranks, tmp_path):
    """--chain: each budget continues the previous budget's checkpoint; the states scored are
    those of the separate 1-rank runs bit for bit (on 3 ranks too: restarts and results are
    rank-count independent), the time is the segments' loop seconds added up (each less its
    checkpoint write)."""
    plain, hit_plain, why_plain = plain_ladder
    chain, hit_chain, why_chain = mpipack_side.ladder(START, ranks, ladder_args(True), str(tmp_path / "chain"))
    assert why_plain == why_chain == "finish_line", (plain[-1], chain[-1])
    assert [r["iterations"] for r in plain] == [r["iterations"] for r in chain]
    assert len(chain) >= 4  # several segments, so restarts were exercised
    for a, b in zip(plain, chain):
        assert a["final"]["W"] == b["final"]["W"] and a["final"]["max_overlap"] == b["final"]["max_overlap"]
    secs = [r["seconds"] for r in chain]
    assert all(s2 > s1 for s1, s2 in zip(secs, secs[1:]))
    assert abs(secs[-1] - sum(r["segment_seconds"] for r in chain)) < 1e-9
    # every budget after the first continued the previous one's checkpoint; no plain one did
    assert chain[0]["restart_from"] is None and all(r["restart_from"] for r in chain[1:])
    assert not any(r["restart_from"] for r in plain)
