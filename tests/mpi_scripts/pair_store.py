"""MPI checks of the pair store (run under ``mpirun -n P``; exit code 0 = all checks passed).

    python pair_store.py migrate OUT_DIR
        Run a 2D DAHA-S scene some iterations, then force a migration of EVERY particle by
        handing each rank's box to the next rank (a permuted copy of the RCB partition) and
        rebuilding; then a normal rebalance. Across each rebuild the set of lambda > 0 pairs and
        their values must be identical, both ends of every pair must hold the same lambda, and
        the rows must contain every partner within d_ij + skin. Then a few more iterations; rank
        0 writes OUT_DIR/final.npz for the cross-rank-count comparison done by the test.

    python pair_store.py far OUT_DIR
        Take a contact (lambda > 0) between spheres a and b, move b (X^n and X^{n-1}) on its
        owner far away, into another rank's box and beyond the ghost cutoff d_max + skin of
        a's box, and rebuild: the pair must survive on both ends, with a and b on different
        ranks (held as far ghosts of each other), and be listed by Solver.gather().

Any failed check raises; the exception is printed and the job is aborted (exit code != 0).
"""

import sys
import traceback
from pathlib import Path

import numpy as np

from mpipack import config
from mpipack.parallel import domain
from mpipack.parallel.comm import Comm
from mpipack.engine.hooks import Hook
from mpipack.engine.loop import run
from mpipack.engine.solver import Solver


def log(comm, *args):
    if comm.rank == 0:
        print(*args, flush=True)


def row_entries(s):
    """All row entries (gid_i, gid_j, lambda) of this rank, lambda = 0 ones included."""
    st = s.state
    counts = np.diff(st.pair_offsets)
    gi = np.repeat(st.gid[: st.n_local], counts)
    gj = st.gid[st.pair_j]
    return gi, gj, st.pair_lambda.copy()


def global_entries(s):
    """Row entries of all ranks, on every rank."""
    parts = s.comm.allgather_object(row_entries(s))
    return tuple(np.concatenate([p[k] for p in parts]) for k in range(3))


def lambda_pairs(s):
    """{(gid_i, gid_j): lambda} for lambda > 0, gid_i < gid_j, after checking that both ends of
    every such pair hold it with the same bits (on every rank)."""
    gi, gj, lam = global_entries(s)
    keep = lam > 0
    ends = {}
    for a, b, l in zip(gi[keep].tolist(), gj[keep].tolist(), lam[keep].tolist()):
        assert (a, b) not in ends, f"pair {(a, b)} appears twice in a row"
        ends[(a, b)] = l
    for (a, b), l in ends.items():
        other = ends.get((b, a))
        assert other is not None, f"pair {(a, b)} has lambda {l} > 0 at {a}'s end only"
        assert np.float64(other).tobytes() == np.float64(l).tobytes(), \
            f"pair {(a, b)}: the ends disagree, {l!r} vs {other!r}"
    return {k: v for k, v in ends.items() if k[0] < k[1]}


def owners(s):
    """{gid: owning rank}, on every rank."""
    parts = s.comm.allgather_object(s.state.gid[: s.state.n_local].copy())
    own = {}
    for r, g in enumerate(parts):
        for x in g.tolist():
            assert x not in own, f"gid {x} owned by ranks {own[x]} and {r}"
            own[x] = r
    assert sorted(own) == list(range(s.n)), "particles lost or duplicated"
    return own


def check_rows_complete(s, fresh=True):
    """Every pair within d_ij + skin (just after a rebuild; fresh=True) or within d_ij (any
    time: the rows stay valid while no particle has moved skin/2) is in the rows, from both
    ends; checked on rank 0."""
    g = s.gather()
    gi, gj, _ = global_entries(s)
    if s.comm.rank != 0:
        return
    present = set(zip(gi.tolist(), gj.tolist()))
    x, d = g["x"], g["diam"]
    r2 = ((x[:, None, :] - x[None, :, :]) ** 2).sum(axis=2)
    rc = 0.5 * (d[:, None] + d[None, :]) + (s.skin if fresh else 0.0)
    i, j = np.nonzero((r2 < rc * rc) & ~np.eye(x.shape[0], dtype=bool))
    need = set(zip(g["gid"][i].tolist(), g["gid"][j].tolist()))
    lost = need - present
    assert not lost, f"{len(lost)} near pairs missing from the rows, e.g. {sorted(lost)[:5]}"


def same_gather(g1, g2, what):
    if g1 is None:
        return
    for k in g1:
        assert np.array_equal(g1[k], g2[k]), f"{what}: gathered '{k}' changed across the rebuild"


def permuted(part, P, shift=1):
    """The partition with rank r's box given to rank (r + shift) % P."""
    perm = (np.arange(P) + shift) % P
    recode = lambda c: np.where(c < 0, -1 - perm[np.clip(-1 - c, 0, P - 1)], c)
    lo = np.empty_like(part.lo)
    hi = np.empty_like(part.hi)
    lo[perm] = part.lo
    hi[perm] = part.hi
    return domain.Partition(part.axis.copy(), part.cut.copy(), recode(part.left),
                            recode(part.right), lo, hi)


def counter_total(s, name):
    return int(s.comm.allreduce(np.array([s.counters[name]], np.int64))[0])


def advance(s, n):
    """n more iterations through the one loop (engine.loop.run); returns the last figures."""
    last = {}
    scene = s.scene.replace(stop={"eps": 0.0, "max_iter": s.state.iteration + n})
    run(scene, s.comm, hooks=[Hook(lambda ctx: last.update(ctx.figures), every=1)], solver=s)
    return last


def migrate(comm, out):
    scene = config.load("paper-2d", ["n=300", "stop.eps=0", "stop.max_iter=1000"])
    s = Solver(scene, comm)
    s.initialise()
    advance(s, 500)
    before = lambda_pairs(s)
    assert len(before) > 100, f"only {len(before)} lambda > 0 pairs: test set-up too weak"
    g0 = s.gather()
    own0 = owners(s)
    check_rows_complete(s, fresh=False)

    # 1. every particle to another rank
    if comm.size > 1:
        s.partition = permuted(s.partition, comm.size)
    s.rebuild(rebalance=False)
    own1 = owners(s)
    moved = sum(own0[k] != own1[k] for k in own0)
    if comm.size > 1:
        assert moved == s.n, f"only {moved} of {s.n} particles migrated"
    after = lambda_pairs(s)
    assert after == before, f"pairs changed across the migration: lost {sorted(set(before) - set(after))[:5]}, gained {sorted(set(after) - set(before))[:5]}"
    same_gather(g0, s.gather(), "migration")
    check_rows_complete(s)
    log(comm, f"migrate: {moved} particles moved, {len(after)} lambda>0 pairs kept")

    # 2. back with a fresh RCB
    s.rebuild(rebalance=True)
    own2 = owners(s)
    moved = sum(own1[k] != own2[k] for k in own1)
    if comm.size > 1:
        assert moved > 0
    assert lambda_pairs(s) == before, "pairs changed across the rebalance"
    same_gather(g0, s.gather(), "rebalance")
    check_rows_complete(s)

    # 3. carry on: the result must not depend on the number of ranks (compared by the test)
    advance(s, 100)
    check_rows_complete(s, fresh=False)
    lambda_pairs(s)
    g = s.gather()
    if comm.rank == 0:
        np.savez(Path(out) / "final.npz", **g)
    log(comm, "migrate: OK")


def box_distance(p, lo, hi):
    q = np.clip(p, lo, hi)
    return float(np.sqrt(((p - q) ** 2).sum()))


def far(comm, out):
    scene = config.load("paper-2d", ["n=300", "stop.eps=0", "stop.max_iter=1000"])
    s = Solver(scene, comm)
    s.initialise()
    advance(s, 500)
    before = lambda_pairs(s)
    own = owners(s)
    g = s.gather()
    choice = None
    if comm.rank == 0:
        x = g["x"]
        P = comm.size
        dirs = []
        for k in range(s.dim):
            for sign in (1.0, -1.0):
                e = np.zeros(s.dim)
                e[k] = sign
                dirs.append(e)
        # prefer the strongest contacts; a on any rank, b's new home another rank
        for (a, b), lam in sorted(before.items(), key=lambda kv: -kv[1]):
            ra = own[a]
            for e in dirs:
                new = x[a] + 60.0 * e
                rb = int(s.partition.owners(new[None, :], 1)[0])
                if P > 1 and rb == ra:
                    continue
                if P > 1 and box_distance(new, s.partition.lo[ra], s.partition.hi[ra]) <= 3 * s.r_ghost:
                    continue
                if P > 1 and box_distance(x[a], s.partition.lo[rb], s.partition.hi[rb]) <= 3 * s.r_ghost:
                    continue
                choice = (a, b, lam, new - x[b], rb)
                break
            if choice:
                break
        assert choice is not None, "no suitable pair found"
    a, b, lam, shift, rb = comm.bcast_object(choice)
    log(comm, f"far: pair ({a}, {b}) lambda {lam!r}: moving {b} from rank {own[b]} to rank {rb}; "
              f"{a} stays on rank {own[a]}")
    st = s.state
    mine = np.flatnonzero(st.gid[: st.n_local] == b)
    if mine.size:
        st.x[mine[0]] += shift
        st.x_prev[mine[0]] += shift
    far0 = counter_total(s, "far_ghosts")
    s.rebuild(rebalance=False)
    own2 = owners(s)
    if comm.size > 1:
        assert own2[b] == rb and own2[a] != own2[b], (own2[a], own2[b], rb)
    after = lambda_pairs(s)
    assert (a, b) in after, f"far pair ({a}, {b}) lost in the rebuild"
    assert after[(a, b)] == lam
    assert after == before, f"pairs changed: lost {sorted(set(before) - set(after))[:5]}"
    g2 = s.gather()
    if comm.rank == 0:
        k = np.flatnonzero((g2["pairs_gid"][:, 0] == a) & (g2["pairs_gid"][:, 1] == b))
        assert k.size == 1 and g2["pairs_lambda"][k[0]] == lam, "gather() does not list the far pair"
        dist = float(np.sqrt(((g2["x"][a] - g2["x"][b]) ** 2).sum()))
        assert dist > 10 * s.r_ghost, dist
    if comm.size > 1:
        assert counter_total(s, "far_ghosts") > far0, "no far ghost was requested"
        # each end holds the other one as a ghost
        st = s.state
        ghosts = set(st.gid[st.n_local:].tolist())
        mine = set(st.gid[: st.n_local].tolist())
        if a in mine:
            assert b in ghosts, f"rank {comm.rank} owns {a} but has no ghost of {b}"
        if b in mine:
            assert a in ghosts, f"rank {comm.rank} owns {b} but has no ghost of {a}"
    check_rows_complete(s)

    # a rebalance with the far sphere in the cloud, then iterations: the pair is released
    # (phi << 0), nothing breaks
    s.rebuild(rebalance=True)
    assert lambda_pairs(s) == before, "pairs changed across the rebalance"
    fig = advance(s, 1)
    assert np.isfinite(fig["relative_change"])
    assert (a, b) not in lambda_pairs(s), "lambda of a far-apart pair should drop to 0"
    advance(s, 20)
    log(comm, "far: OK")


def main():
    comm = Comm()
    mode, out = sys.argv[1], sys.argv[2]
    try:
        {"migrate": migrate, "far": far}[mode](comm, out)
    except BaseException:
        traceback.print_exc()
        sys.stdout.flush()
        sys.stderr.flush()
        if comm.size > 1:
            comm.abort(1)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
