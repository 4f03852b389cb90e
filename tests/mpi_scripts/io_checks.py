"""MPI workers for tests/test_io.py (run under ``mpirun -n P``; exit code 0 = checks passed).

    python io_checks.py snapshots OUT            write the snapshot cases under OUT, convert two to VTK
    python io_checks.py ckpt-write PATH SEED [--serial] [--verify]
                                                 checkpoint of reference SEED, unequal blocks, one empty
    python io_checks.py ckpt-read PATH SEED [--serial]   read on P ranks, compare bitwise
    python io_checks.py ckpt-kill PATH           write seed 1, then die (SIGKILL, last rank) inside the
                                                 write of seed 2, before its temporary file is closed
                                                 (leaves PATH.killed as proof)
    python io_checks.py ckpt-errors PATH...      read each; print one JSON line per rank and file

The io layer uses only ``comm.mpi``, ``comm.rank`` and ``comm.size``: a namespace stands in for
mpipack.parallel.comm.Comm. The reference data are functions of (N, dim, seed) only, imported by the test
process to check the files.
"""

import json
import os
import signal
import sys
from types import SimpleNamespace

import numpy as np

from mpipack.io import (CheckpointError, SnapshotWriter, convert_run, read_checkpoint,
                        write_checkpoint)
from mpipack.io import _h5, checkpoint

# ---- reference data (also imported by tests/test_io.py) --------------------------------------

SNAP_CASES = {  # name: (N, dim, empty rank or None)
    "2d": (1500, 2, None),
    "3d-empty0": (700, 3, 0),
    "1d": (300, 1, None),
}
SNAP_ITERS = (0, 50, 100)
SNAP_VARIANTS = {  # name: SnapshotWriter keyword arguments
    "auto": {},
    "points": {"method": "points"},
    "serial": {"parallel": False},
    "mpio": {"parallel": True},
    "nompi": {},  # h5py_has_mpi() patched to False: the fallback with its warning
}
CKPT_N, CKPT_DIM = 1201, 3


def make_comm():
    from mpi4py import MPI
    w = MPI.COMM_WORLD
    return SimpleNamespace(mpi=w, rank=w.Get_rank(), size=w.Get_size())


def snapshot_fields(n, dim, iteration):
    """Full (N, ...) reference fields of one snapshot, in gid order."""
    rng = np.random.default_rng([n, dim, iteration])
    return {"position": rng.normal(size=(n, dim)) * 10.0,
            "diameter": rng.uniform(0.5, 1.5, n),
            "pressure": rng.exponential(size=n) * (rng.random(n) < 0.7),
            "contacts": rng.integers(0, 13, n).astype(np.int32)}


def snapshot_attrs(iteration):
    return {"iteration": iteration, "wall_seconds": 0.25 * iteration, "relative_change": 1.0 / (1 + iteration),
            "max_overlap": 1e-3 / (1 + iteration), "W": 3.0 + 1.0 / (1 + iteration)}


def scatter_gids(n, size, seed, empty=None):
    """A random permutation of 0..n-1 cut into `size` pieces of random sizes (rank `empty`
    gets none): particles owned by space have gids in no order."""
    rng = np.random.default_rng([seed, n, size])
    perm = rng.permutation(n)
    cuts = np.sort(rng.integers(0, n + 1, size - 1))
    pieces = np.split(perm, cuts)
    if empty is not None and size > 1:
        other = (empty + 1) % size
        pieces[other] = np.concatenate([pieces[other], pieces[empty]])
        pieces[empty] = perm[:0]
    return pieces


def checkpoint_reference(seed, n=CKPT_N, dim=CKPT_DIM):
    """Full state in gid order: per-particle arrays and the symmetric pair history as CSR.
    Even seeds carry NAP/NAV's x_lin, odd seeds do not; seeds >= 100 have an empty history
    (a checkpoint at iteration 0), others about 6 partners per particle."""
    partners = 0 if seed >= 100 else 6
    rng = np.random.default_rng([seed, n, dim])
    x = rng.normal(size=(n, dim))
    ref = {"x": x, "x_prev": x + 1e-3 * rng.normal(size=(n, dim)),
           "diam": rng.uniform(0.8, 1.2, n),
           "phase": rng.integers(-5, 5, (n, 2)).astype(np.int16)}  # an extra per-particle array
    if seed % 2 == 0:
        ref["x_lin"] = x + 1e-6 * rng.normal(size=(n, dim))
    npairs = partners * n // 2
    i = rng.integers(0, n, npairs)
    j = rng.integers(0, n, npairs)
    keep = i != j
    pairs = np.unique(np.sort(np.stack([i[keep], j[keep]], 1), axis=1), axis=0)
    lam = rng.exponential(size=len(pairs))
    a = np.concatenate([pairs[:, 0], pairs[:, 1]])
    b = np.concatenate([pairs[:, 1], pairs[:, 0]])
    lam2 = np.concatenate([lam, lam])
    order = np.lexsort((b, a))
    a, b, lam2 = a[order], b[order], lam2[order]
    ref["hist_count"] = np.bincount(a, minlength=n).astype(np.int64)
    ref["hist_gid"] = b.astype(np.int64)
    ref["hist_lambda"] = lam2
    ref["hist_age"] = (np.arange(len(a)) % 7).astype(np.int32)  # an extra per-entry array
    return ref


def checkpoint_scalars(seed):
    """Floats that JSON must reproduce bit for bit."""
    rng = np.random.default_rng(seed)
    bits = rng.integers(0, 2 ** 63, 200, dtype=np.int64).view(np.float64)
    bits = [float(v) for v in bits if np.isfinite(v)]
    return {"iteration": 1000 + seed, "lambda_fresh": bool(seed % 2), "seed": seed,
            "counters": {"rebuilds": 17, "rebalances": 3},
            "floats": bits + [0.1, 1.0 / 3.0, 5e-324, -0.0, 2.2250738585072014e-308,
                              1.7976931348623157e308, float("nan"), float("inf"), float("-inf")],
            "controller": {"gamma": float(np.sqrt(7.8e-3 * 2.8e3)), "history": [1e-5, 2.5e-7]}}


def same_scalars(a, b):
    """Equality with float64 bits compared (NaN == NaN, -0.0 != 0.0)."""
    if isinstance(a, float) and isinstance(b, float):
        return np.array(a).view(np.int64) == np.array(b).view(np.int64)
    if type(a) is not type(b):
        return False
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(same_scalars(a[k], b[k]) for k in a)
    if isinstance(a, list):
        return len(a) == len(b) and all(same_scalars(u, v) for u, v in zip(a, b))
    return a == b


def block_of(ref, lo, hi):
    off = np.concatenate(([0], np.cumsum(ref["hist_count"])))
    blk = {"gid_lo": lo}
    for k, v in ref.items():
        blk[k] = v[off[lo]:off[hi]] if k in ("hist_gid", "hist_lambda", "hist_age") else v[lo:hi]
    return blk


def writer_cuts(n, size, seed):
    """Unequal consecutive blocks, one of them empty (rank 0 on 2 ranks, rank 1 on 3 or more)."""
    rng = np.random.default_rng([seed, size, 7])
    cuts = [0] + sorted(rng.integers(0, n + 1, size - 1).tolist()) + [n]
    if size > 2:
        cuts[2] = cuts[1]
    elif size == 2:
        cuts[1] = 0
    return cuts


# ---- actions ----------------------------------------------------------------------------------

def do_snapshots(comm, out):
    for case, (n, dim, empty) in SNAP_CASES.items():
        mine = scatter_gids(n, comm.size, seed=11, empty=empty)[comm.rank]
        for variant, kw in SNAP_VARIANTS.items():
            folder = os.path.join(out, case, variant)
            if comm.rank == 0:
                os.makedirs(folder, exist_ok=True)
            comm.mpi.Barrier()
            saved = _h5.h5py_has_mpi
            if variant == "nompi":
                _h5.h5py_has_mpi = lambda: False
            try:
                path = os.path.join(folder, "snapshots.h5")
                attrs = {"scene": json.dumps({"name": case, "n": n, "dim": dim}), "parameters": {"alpha": 7.8e-3},
                         "ranks": comm.size}
                # first a writer for two snapshots, then a second one appending (a continued run)
                w = SnapshotWriter(comm, path, n, dim, attrs, **kw)
                for it in SNAP_ITERS[:2]:
                    full = snapshot_fields(n, dim, it)
                    w.write(mine, {k: v[mine] for k, v in full.items()}, snapshot_attrs(it))
                w.close()
                with SnapshotWriter(comm, path, n, dim, attrs, **kw) as w:
                    for it in SNAP_ITERS[2:]:
                        full = snapshot_fields(n, dim, it)
                        w.write(mine, {k: v[mine] for k, v in full.items()}, snapshot_attrs(it))
            finally:
                _h5.h5py_has_mpi = saved
        for variant in ("auto",):
            convert_run(comm, os.path.join(out, case, variant))


def do_ckpt_write(comm, path, seed, serial, verify):
    ref = checkpoint_reference(seed)
    cuts = writer_cuts(CKPT_N, comm.size, seed)
    blk = block_of(ref, cuts[comm.rank], cuts[comm.rank + 1])
    attrs = {"scene": json.dumps({"n": CKPT_N}), "ranks": comm.size, "seed": seed}
    t = write_checkpoint(comm, path, CKPT_N, CKPT_DIM, blk, checkpoint_scalars(seed), attrs,
                         parallel=False if serial else None)
    assert isinstance(t, float) and t > 0, t
    ts = comm.mpi.allgather(t)
    assert all(v == t for v in ts), ts
    if verify:
        do_ckpt_read(comm, path, seed, serial)


def do_ckpt_read(comm, path, seed, serial):
    ref = checkpoint_reference(seed)
    blk, scalars, attrs = read_checkpoint(comm, path, parallel=False if serial else None)
    lo, hi = (CKPT_N * comm.rank) // comm.size, (CKPT_N * (comm.rank + 1)) // comm.size
    want = block_of(ref, lo, hi)
    assert set(blk) == set(want), (sorted(blk), sorted(want))
    assert blk["gid_lo"] == lo
    for k, v in want.items():
        if k == "gid_lo":
            continue
        assert blk[k].dtype == v.dtype and blk[k].shape == v.shape, (k, blk[k].dtype, v.dtype, blk[k].shape, v.shape)
        assert np.array_equal(blk[k].view(np.uint8), np.ascontiguousarray(v).view(np.uint8)), f"{k} differs"
    assert same_scalars(scalars, json.loads(json.dumps(checkpoint_scalars(seed)))), "scalars differ"
    assert same_scalars(scalars, checkpoint_scalars(seed)), "scalars differ from the written floats"
    assert attrs["format"] == "mpipack-checkpoint" and attrs["format_version"] == 1, attrs
    assert attrs["seed"] == seed and attrs["n"] == CKPT_N and attrs["dim"] == CKPT_DIM, attrs
    line = f"OK rank {comm.rank}: gids [{lo}, {hi}) entries {len(blk['hist_gid'])}"
    # rank 0 prints every rank's line (lines printed by several ranks can interleave)
    for l in comm.mpi.gather(line, root=0) or []:
        print(l, flush=True)


def do_ckpt_kill(comm, path):
    do_ckpt_write(comm, path, 1, False, False)
    comm.mpi.Barrier()

    def die(stage, c):
        if stage == "data_written" and c.rank == c.size - 1:
            # a marker file rather than a printed line: output in flight may be lost when
            # mpirun tears the job down
            with open(path + ".killed", "w") as f:
                f.write(f"rank {c.rank} of {c.size}: SIGKILL inside the checkpoint write\n")
            os.kill(os.getpid(), signal.SIGKILL)

    checkpoint._test_hook = die
    do_ckpt_write(comm, path, 2, False, False)
    print("the killed write returned", flush=True)
    sys.exit(3)


def do_ckpt_errors(comm, paths):
    for p in paths:
        try:
            read_checkpoint(comm, p)
            msg = None
        except CheckpointError as e:
            msg = str(e)
        # rank 0 prints every rank's message (lines printed by several ranks can interleave)
        for r, m in enumerate(comm.mpi.gather(msg, root=0) or []):
            print(json.dumps({"rank": r, "path": p, "error": m}), flush=True)


def main(argv):
    comm = make_comm()
    action, args = argv[0], argv[1:]
    flags = {a for a in args if a.startswith("--")}
    args = [a for a in args if not a.startswith("--")]
    if action == "snapshots":
        do_snapshots(comm, args[0])
    elif action == "ckpt-write":
        do_ckpt_write(comm, args[0], int(args[1]), "--serial" in flags, "--verify" in flags)
    elif action == "ckpt-read":
        do_ckpt_read(comm, args[0], int(args[1]), "--serial" in flags)
    elif action == "ckpt-kill":
        do_ckpt_kill(comm, args[0])
    elif action == "ckpt-errors":
        do_ckpt_errors(comm, args)
    else:
        raise SystemExit(f"unknown action {action}")


if __name__ == "__main__":
    try:
        main(sys.argv[1:])
    except BaseException as e:
        if isinstance(e, SystemExit) and not e.code:
            raise
        import traceback
        traceback.print_exc()
        sys.stdout.flush()
        sys.stderr.flush()
        # one failing rank must not leave the others waiting in a collective
        from mpi4py import MPI
        MPI.COMM_WORLD.Abort(1)
