"""The scaling model (``experiments.scaling``) on hand-built count rows: each kind of traffic is
costed by its own law, and beyond the measured ranks each kind's latency grows as its
algorithm does (point to point: constant; an alltoall: K - 1; tree collectives and barriers:
log2 K). The counts themselves: tests/test_comm_counts.py."""

import math

import pytest

from mpipack.experiments import scaling

L, B = 1e-6, 1e10  # latency (s) and bandwidth (bytes/s) of the test's network


def row(k, per_rank, iterations=10, n=1000):
    """A count row of k ranks, every rank with the same totals ``per_rank``."""
    return {"case": "gaussian", "dim": 3, "n": n, "ranks": k, "iterations": iterations,
            "totals": [dict(per_rank) for _ in range(k)], "local_mean": [n / k] * k,
            "rebuilds": [1] * k, "ghosts_mean": [0] * k, "ghosts_max": [0] * k, "far_ghosts": [0] * k}


def test_each_kind_is_costed_by_its_law():
    r = row(8, {"forward.p2p": [20, 0], "reduce.allreduce": [10, 0], "exchange.alltoall": [10, 0],
                "borders.barrier": [10, 0], "far.allgather": [10, 0]})
    parts = scaling.iteration_comm(r, 8, L, B)
    lg = math.ceil(math.log2(8))
    assert parts["forward"] == pytest.approx(2 * L)
    assert parts["reductions"] == pytest.approx(lg * L)
    assert parts["rebuild"] == pytest.approx((8 - 1) * L + lg * L + lg * L)
    only_p2p = scaling.iteration_comm(r, 8, L, B, growth="const")
    assert only_p2p == pytest.approx({"forward": 2 * L, "reductions": 0.0, "rebuild": 0.0})
    linear = scaling.iteration_comm(r, 8, L, B, growth="linear")
    assert linear["rebuild"] == pytest.approx(7 * L) and linear["forward"] == 0.0


@pytest.mark.parametrize("kind, growth", [("p2p", lambda k: 1.0), ("alltoall", lambda k: (k - 1) / 31),
                                          ("barrier", lambda k: math.ceil(math.log2(k)) / 5)])
def test_latencies_beyond_the_measured_ranks_grow_as_their_algorithm(kind, growth):
    """Rebuild traffic of one kind measured at K = 32; at K = 1024 its latency per iteration is
    the measured one times 1, 1023/31 or 10/5."""
    k_ref = 32
    rows = {("gaussian", 3, 1000, k_ref): row(k_ref, {"exchange." + kind: [10, 0], "reduce.allreduce": [10, 0]})}
    bench = {(3, 1): {1000: 1e-7, 100000: 1e-7}, (3, 2): {100000: 1e-7}}
    pred, _, _ = scaling.predict(rows, bench, "gaussian", 3, 1000, L, 1e300)
    at = {p["K"]: p for p in pred}
    assert at[32]["src"] == "measured" and at[1024]["src"] == "law"
    assert at[1024]["rebuild"] == pytest.approx(at[32]["rebuild"] * growth(1024), rel=1e-12)
    assert at[1024]["reductions"] == pytest.approx(at[32]["reductions"] * 10 / 5, rel=1e-12)
