"""MPI checks of the communication layer and the RCB partition (run under mpirun -n P).

    python comm_checks.py

reduce_fused (exact integer sums, maxima with NaN winning and Inf kept), exact sums split over
ranks, allreduce, alltoallv (ragged rows; sparse patterns call after call, ranks out of step),
and the RCB partition of an initial cloud (balanced, every particle inside its own box,
owners() consistent with the boxes). Exit code 0 = all checks passed.
"""

import sys
import traceback

import numpy as np

from mpipack import config
from mpipack.parallel import exactsum
from mpipack.parallel.comm import Comm
from mpipack.engine.solver import Solver


def check_reductions(comm):
    r, P = comm.rank, comm.size
    sums = np.array([[r, -2 * r], [2 ** 40 + r, 7]], dtype=np.int64)
    nan_rank = P - 1
    maxima = np.array([1.5 * r, 0.0, np.nan if r == nan_rank else float(r),
                       np.inf if r == 0 else 1.0, 1e-300 * (r + 1)])
    g_sums, g_max = comm.reduce_fused(sums, maxima)
    tot = sum(range(P))
    assert g_sums.shape == sums.shape and g_sums.dtype == np.int64
    assert g_sums.tolist() == [[tot, -2 * tot], [P * 2 ** 40 + tot, 7 * P]], g_sums
    assert g_max[0] == 1.5 * (P - 1) and g_max[1] == 0.0
    assert np.isnan(g_max[2]), g_max
    assert g_max[3] == np.inf
    assert g_max[4] == 1e-300 * P
    # inputs untouched
    assert sums[0, 0] == r and (r == nan_rank) == bool(np.isnan(maxima[2]))

    # exact sums: every rank accumulates its slice of the same array
    rng = np.random.default_rng(99)
    v = (10.0 ** rng.uniform(-10, 10, 50_001)) * rng.choice([-1.0, 1.0], 50_001)
    lo, hi = len(v) * r // P, len(v) * (r + 1) // P
    acc = exactsum.new_accumulator(2)
    exactsum.accumulate(np.ascontiguousarray(v[lo:hi]), acc, 1)
    g, _ = comm.reduce_fused(acc, np.zeros(0))
    assert exactsum.value(g, 1) == exactsum.exact_sum(v), (exactsum.value(g, 1), exactsum.exact_sum(v))
    assert exactsum.value(g, 0) == 0.0

    a = comm.allreduce(np.array([r, -r], dtype=np.int64), op="max")
    assert a.tolist() == [P - 1, 0]
    a = comm.allreduce(np.array([float(r)]), op="min")
    assert a.tolist() == [0.0]


def check_alltoallv(comm):
    """Ragged rows of several dtypes and shapes, rank r sending (r + q) % 3 rows of each
    array to rank q (none to some), every row labelled by (source, destination, row)."""
    r, P = comm.rank, comm.size

    def rows(src, dst):
        return (src + dst) % 3

    send, counts = {}, {}
    for name, kind in (("x", (np.float64, (2,))), ("gid", (np.int64, ())), ("flag", (np.bool_, ())),
                       ("tag", (np.int32, ())), ("trip", (np.uint8, (3,)))):
        dtype, shape = kind
        blocks = []
        for q in range(P):
            n = rows(r, q) + (1 if name == "gid" else 0)  # another count per name
            label = np.array([1000 * r + 10 * q + i for i in range(n)])
            blocks.append(np.broadcast_to((label % 256 if dtype == np.uint8 else label % 2 == 1 if dtype == np.bool_
                                           else label).reshape((n,) + (1,) * len(shape)), (n,) + shape).astype(dtype))
        send[name] = np.concatenate(blocks) if blocks else np.zeros((0,) + shape, dtype)
        counts[name] = np.array([b.shape[0] for b in blocks], dtype=np.int64)
    got, rcounts = comm.alltoallv(send, counts)
    for name, a in send.items():
        want_counts = [rows(s, r) + (1 if name == "gid" else 0) for s in range(P)]
        assert rcounts[name].tolist() == want_counts, (name, rcounts[name])
        labels = np.concatenate([[1000 * s + 10 * r + i for i in range(want_counts[s])] for s in range(P)])
        b = got[name]
        assert b.dtype == a.dtype and b.shape == (len(labels),) + a.shape[1:], (name, b.dtype, b.shape)
        if a.dtype == np.uint8:
            labels = labels % 256
        elif a.dtype == np.bool_:
            labels = labels % 2 == 1
        width = int(np.prod(a.shape[1:]))
        want = np.repeat(np.asarray(labels).reshape(-1, 1), width, axis=1).astype(a.dtype)
        assert np.array_equal(b.reshape(len(labels), width), want), name


def check_sparse_rounds(comm):
    """40 alltoallv calls in a row with sparse, changing patterns (most pairs empty; a call where
    nobody sends; one where only rank 0 does), the ranks out of step (a rank sleeps before some
    calls, so another may be a call ahead): every rank gets exactly its rows, by source rank."""
    import time

    r, P = comm.rank, comm.size
    for call in range(40):
        rng = np.random.default_rng(call)  # the same pattern on every rank
        rows = rng.integers(1, 4, (P, P)) * (rng.random((P, P)) < 0.35)
        if call == 5:
            rows[:] = 0
        if call == 6:
            rows[1:] = 0
        label = lambda s, q: np.array([100000 * call + 100 * s + 10 * q + i for i in range(rows[s, q])],  # noqa: E731
                                      dtype=np.int64)
        send = {"v": np.concatenate([label(r, q) for q in range(P)]),
                "w": np.concatenate([label(r, q).astype(np.float64).repeat(2).reshape(-1, 2) for q in range(P)])}
        if (call + r) % 7 == 3:
            time.sleep(0.01)
        got, rc = comm.alltoallv(send, {"v": rows[r], "w": rows[r]})
        want = np.concatenate([label(s, r) for s in range(P)])
        assert rc["v"].tolist() == rows[:, r].tolist(), (call, rc["v"], rows[:, r])
        assert np.array_equal(got["v"], want), (call, got["v"], want)
        assert np.array_equal(got["w"], want.astype(np.float64).repeat(2).reshape(-1, 2)), call


def check_partition(comm):
    scene = config.load(None, ["n=301", "stop.eps=0"])
    s = Solver(scene, comm)
    s.initialise()
    st, part = s.state, s.partition
    n_local = st.n_local
    counts = comm.allgather_object(n_local)
    assert sum(counts) == 301
    assert max(counts) - min(counts) <= 1, counts
    x = st.x[:n_local]
    lo, hi = part.lo[comm.rank], part.hi[comm.rank]
    assert np.all(x >= lo) and np.all(x < hi), "a particle outside its owner's box"
    assert np.all(part.owners(x, n_local) == comm.rank)
    # boxes tile space: a random point has exactly one box, the one owners() names
    rng = np.random.default_rng(5)
    pts = rng.normal(scale=3.0, size=(2000, s.dim))
    own = part.owners(pts, pts.shape[0])
    inside = np.all((pts[:, None, :] >= part.lo[None]) & (pts[:, None, :] < part.hi[None]), axis=2)
    assert np.all(inside.sum(axis=1) == 1)
    assert np.array_equal(np.argmax(inside, axis=1), own)
    # ghosts: every remote particle within d_max + skin of my box is here
    g = s.gather()
    g = comm.bcast_object(g)
    d2 = ((np.clip(g["x"], lo, hi) - g["x"]) ** 2).sum(axis=1)
    near = set(g["gid"][d2 < s.r_ghost ** 2].tolist()) - set(st.gid[:n_local].tolist())
    have = set(st.gid[n_local:].tolist())
    assert near <= have, f"missing ghosts {sorted(near - have)[:5]}"


def main():
    comm = Comm()
    try:
        check_reductions(comm)
        check_alltoallv(comm)
        check_sparse_rounds(comm)
        check_partition(comm)
    except BaseException:
        traceback.print_exc()
        sys.stdout.flush()
        sys.stderr.flush()
        if comm.size > 1:
            comm.abort(1)
        return 1
    if comm.rank == 0:
        print("comm: OK", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
