"""The communication counters (``parallel.comm.Counts``) and ``experiments.scaling count``:
one rank sends nothing; on 2 and 3 ranks a 1D chain cut into slabs sends what its topology
says (one forward message per neighbouring slab per iteration, its ghosts' coordinates, one
fused allreduce); counting changes no result, bit for bit. Nothing here is timed."""

import json
import sys
import textwrap

import pytest

from conftest import describe, mpirun


def count(P, tmp_path, case, dim, n, iters):
    out = tmp_path / "counts.jsonl"
    proc = mpirun(P, [sys.executable, "-m", "mpipack.experiments.scaling", "count", "--case", case,
                      "--dim", dim, "--n", n, "--iters", iters, "--json", out], cwd=tmp_path)
    assert proc.returncode == 0, describe(proc)
    rows = [json.loads(line) for line in out.read_text().splitlines()]
    assert len(rows) == 1 and rows[0]["ranks"] == P and rows[0]["iterations"] == iters, rows
    return rows[0]


def test_one_rank_sends_nothing():
    """On one rank every verb takes its size-1 short cut: no category is ever charged, no ghost."""
    from mpipack.experiments.scaling import count_case
    from mpipack.parallel.comm import Comm

    row = count_case(Comm.serial(), "gaussian", 2, 400, 40)
    assert row["iterations"] == 40 and row["ranks"] == 1
    assert row["totals"] == [{}] and row["setup"] == [{}], row
    assert row["ghosts_max"] == [0] and row["local_final"] == [400]


@pytest.mark.parametrize("P", [2, 3])
def test_a_chain_in_slabs_sends_what_its_topology_says(P, tmp_path):
    """1D lattice chain, N = 300 on P slabs: the end slabs have one neighbour, the inner ones
    two. Per iteration each rank sends one forward message per neighbour, carrying 8 bytes per
    coordinate of the rows that are ghosts elsewhere (so the ranks' bytes add up to 8 x the
    ghosts), and makes one fused allreduce; the lattice stays put, so nothing is rebuilt. The
    set-up's one ghost exchange sends its counts, then x, gid and diam: four messages per
    neighbour and one non-blocking barrier, no alltoall (no message to a rank that is no
    neighbour)."""
    iters = 20
    row = count(P, tmp_path, "lattice", 1, 300, iters)
    neighbours = sorted(t["forward.p2p"][0] // iters for t in row["totals"])
    assert neighbours == [1, 1] + [2] * (P - 2), row["totals"]
    for t, setup in zip(row["totals"], row["setup"]):
        m, b = t["forward.p2p"]
        assert m % iters == 0 and b % (8 * iters) == 0 and b > 0
        assert t["reduce.allreduce"][0] == iters
        assert set(t) == {"forward.p2p", "reduce.allreduce"}, t  # no rebuild, no check, nothing else
        assert setup["borders.p2p"][0] == 4 * (m // iters), setup
        assert setup["borders.barrier"][0] == 1 and not any(k.endswith(".alltoall") for k in setup), setup
    sent_rows = sum(t["forward.p2p"][1] for t in row["totals"]) // (8 * iters)
    assert sent_rows == sum(row["ghosts_max"]) == round(sum(row["ghosts_mean"])) > 0
    assert max(row["rebuilds"]) == 0 and max(row["far_ghosts"]) == 0


SCRIPT = textwrap.dedent("""
    import sys
    import numpy as np
    from mpipack import config
    from mpipack.engine.loop import run
    from mpipack.parallel.comm import Comm

    comm = Comm()
    scene = config.load("default", ["dim=2", "n=600", "stop.max_iter=120", "seed=3"])
    out = []
    for counting in (False, True, False):
        counts = comm.count(counting)
        solver, res = run(scene, comm)
        comm.count(False)
        d = solver.gather()
        out.append(d)
        if counting and comm.size > 1:
            rows = counts.rows
            sent = sum(v[1] for kinds in rows.values() for v in kinds.values())
            assert res["rebuilds"] > 2 and sent > 0, (res["rebuilds"], rows)
            assert rows["borders"]["p2p"][0] > 0 and rows["forward"]["p2p"][0] > 0, rows
    if comm.rank == 0:
        for key in ("gid", "x", "x_prev", "pairs_gid", "pairs_lambda"):
            assert out[0][key].tobytes() == out[1][key].tobytes() == out[2][key].tobytes(), key
        np.save(sys.argv[1], out[1]["x"])
        print("same bits")
""")


@pytest.mark.parametrize("P", [2, 3])
def test_counting_changes_no_result(P, tmp_path):
    """The default scene (Gaussian start, rebuilds and migrations), 120 iterations: the positions
    with the counters on are the same bits as without, and as on one rank."""
    script = tmp_path / "same_bits.py"
    script.write_text(SCRIPT)
    x = {}
    for ranks in (1, P):
        proc = mpirun(ranks, [sys.executable, script, tmp_path / f"x{ranks}.npy"], cwd=tmp_path)
        assert proc.returncode == 0 and "same bits" in proc.stdout, describe(proc)
        x[ranks] = (tmp_path / f"x{ranks}.npy").read_bytes()
    assert x[1] == x[P]


FUSED = textwrap.dedent("""
    import numpy as np
    from mpi4py import MPI
    from mpipack.parallel import comm as C

    comm = C.Comm()
    r, P = comm.rank, comm.size
    rng = np.random.default_rng(100 + r)
    for n_sum in (3, 1000, 5000, 40000):
        sums = np.arange(n_sum, dtype=np.int64) * (r + 1) - 7
        g, m = comm.reduce_fused(sums, np.array([1.0 + r, 0.5, np.nan if r == 0 else 0.0]))
        assert np.array_equal(g, np.arange(n_sum, dtype=np.int64) * (P * (P + 1) // 2) - 7 * P), n_sum
        assert m[0] == P and m[1] == 0.5 and np.isnan(m[2]), (n_sum, m)
        # the compiled op against the Python one, on the same packed buffers: the same bits
        maxima = rng.random(n_sum // 2 + 1) * 10.0 ** rng.integers(-300, 300, n_sum // 2 + 1)
        maxima[rng.random(maxima.size) < 0.01] = np.inf
        buf = np.empty(2 + n_sum + maxima.size, dtype=np.int64)
        C._pack(rng.integers(-2**40, 2**40, n_sum), maxima, buf)
        outs = []
        for op in (C._fused_op(), MPI.Op.Create(C._fused_op_fn, commute=True)):
            out = np.empty_like(buf)
            whole = C._fused_type(buf.size)
            comm.mpi.Allreduce([buf, 1, whole], [out, 1, whole], op=op)
            outs.append(out)
        assert np.array_equal(outs[0], outs[1]), n_sum
    if P > 1:
        assert C._FUSED_OP_KIND == "compiled", C._FUSED_OP_KIND
    print("fused OK")
""")


@pytest.mark.parametrize("P", [1, 2, 3])
def test_the_fused_reduction_of_a_large_buffer(P, tmp_path):
    """The fused allreduce's op reads its layout from the buffer's header, so MPI must hand it
    whole buffers: with a plain int64 count, Open MPI's segmented algorithms gave wrong sums
    and maxima from 1000 int64 on 2 ranks (and from the loop's 32 on 32 ranks). The op is the
    compiled one (registered through ctypes), bit for bit the Python op's results."""
    script = tmp_path / "fused.py"
    script.write_text(FUSED)
    proc = mpirun(P, [sys.executable, script], cwd=tmp_path)
    assert proc.returncode == 0 and "fused OK" in proc.stdout, describe(proc)
