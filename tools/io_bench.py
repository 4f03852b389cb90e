"""Write throughput of snapshots and checkpoints, beside the disk's own rate.

    python tools/io_bench.py [--n 1e6] [--dims 2 3] [--ranks 1 2] [--reps 3] [--dir DIR] [--methods]
    mpirun -n P python tools/io_bench.py --worker [...]    (one rank count; prints JSON rows)

Without ``--worker`` the script runs itself under ``mpirun -n P`` for each rank count, runs
``dd if=/dev/zero of=... bs=1M count=<file size> conv=fsync`` for a file of each size, and
prints one table. Synthetic data, N particles in a box cut into P slabs along x (particles owned
by space, so every rank holds gids scattered over 0..N-1, as after a Gaussian start):

    snapshot      position (N, b), diameter, pressure (float64), contacts (int32): one
                  SnapshotWriter.write() in global-id order (alltoallv + collective hyperslabs),
                  into the page cache as in a run (no fsync, "page cache" column); "incl. fsync"
                  adds an fsync of the file (what the disk itself must absorb)
    checkpoint    x, x_prev (N, b), diam, the history CSR with 3 (2D) or 6 (3D) partners per
                  sphere (offset (N+1,) int64, gid int64, lambda float64): write_checkpoint,
                  which includes its fsync and atomic rename; the rows are already in gid blocks
                  (the solver's redistribution is not counted)

MB/s = file payload bytes / median wall time over --reps writes after one untimed warm-up write
(1 MB = 1e6 bytes). dd's rate is the median of --reps runs. Before each rank count, --warm-mb
MiB are written and deleted so that every write lands in recycled page-cache pages, like dd's
(see warm_page_pool: on a VM, first-touch memory is slow). ``--methods`` also times both ways of putting snapshot rows in gid
order (redistribution and point selection) on the largest rank count.
"""

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)


def snapshot_bytes(n, dim):
    return n * (8 * dim + 8 + 8 + 4)


def partners(dim):
    return {1: 2, 2: 3, 3: 6}[dim]


def checkpoint_bytes(n, dim):
    k = partners(dim) * n
    return n * (16 * dim + 8) + 8 * (n + 1) + 16 * k


# ---- worker (under mpirun) ---------------------------------------------------------------------

def worker(args):
    from types import SimpleNamespace

    from mpi4py import MPI

    from mpipack.io import SnapshotWriter, write_checkpoint
    from mpipack.io import _h5

    w = MPI.COMM_WORLD
    comm = SimpleNamespace(mpi=w, rank=w.Get_rank(), size=w.Get_size())
    n = int(float(args.n))
    rows = []
    for dim in args.dims:
        rng = np.random.default_rng([dim, comm.rank])
        # each gid's random position puts it in one of P slabs; rank r owns slab r's gids
        gen = np.random.default_rng([dim, 12345])
        slab = gen.integers(0, comm.size, n)          # the same on every rank
        gid = np.flatnonzero(slab == comm.rank).astype(np.int64)
        m = len(gid)
        fields = {"position": rng.normal(size=(m, dim)), "diameter": rng.uniform(0.9, 1.1, m),
                  "pressure": rng.exponential(size=m),
                  "contacts": rng.integers(0, 13, m).astype(np.int32)}
        folder = args.dir
        path = os.path.join(folder, f"snap_{dim}d_{comm.size}.h5")
        methods = ["redistribute", "points"] if (args.methods and comm.size > 1) else ["redistribute"]
        for method in methods:
            if comm.rank == 0 and os.path.exists(path):
                os.remove(path)
            w.Barrier()
            sw = SnapshotWriter(comm, path, n, dim, {"scene": "{}"}, method=method)
            sw.write(gid, fields, {"iteration": 0})   # warm-up: creates /topology once
            times, times_sync = [], []
            for rep in range(args.reps):
                w.Barrier()
                t0 = time.perf_counter()
                sw.write(gid, fields, {"iteration": rep + 1})
                w.Barrier()
                t1 = time.perf_counter()
                if comm.rank == 0:
                    _h5.fsync_path(path)
                w.Barrier()
                t2 = time.perf_counter()
                times.append(t1 - t0)
                times_sync.append(t2 - t0)
            sw.close()
            if comm.rank == 0:
                os.remove(path)
                os.remove(os.path.splitext(path)[0] + ".xmf")
            rows.append({"kind": "snapshot", "method": method, "dim": dim, "ranks": comm.size, "n": n,
                         "bytes": snapshot_bytes(n, dim), "seconds": times, "seconds_fsync": times_sync})

        # checkpoint: this rank's gid block, with a history of partners(dim) entries per sphere
        lo, hi = _h5.gid_block(n, comm.size, comm.rank)
        mb = hi - lo
        k = partners(dim)
        block = {"gid_lo": lo, "x": rng.normal(size=(mb, dim)), "x_prev": rng.normal(size=(mb, dim)),
                 "diam": rng.uniform(0.9, 1.1, mb), "hist_count": np.full(mb, k, dtype=np.int64),
                 "hist_gid": rng.integers(0, n, mb * k).astype(np.int64),
                 "hist_lambda": rng.exponential(size=mb * k)}
        cpath = os.path.join(folder, f"ckpt_{dim}d_{comm.size}.h5")
        write_checkpoint(comm, cpath, n, dim, block, {"iteration": -1}, {})  # warm-up
        times = []
        for rep in range(args.reps):
            w.Barrier()
            times.append(write_checkpoint(comm, cpath, n, dim, block, {"iteration": rep}, {}))
        if comm.rank == 0:
            os.remove(cpath)
        rows.append({"kind": "checkpoint", "method": "", "dim": dim, "ranks": comm.size, "n": n,
                     "bytes": checkpoint_bytes(n, dim), "seconds": times, "seconds_fsync": times})
    if comm.rank == 0 and args.worker:
        for r in rows:
            print("ROW " + json.dumps(r), flush=True)
    return rows if comm.rank == 0 else None


# ---- driver ------------------------------------------------------------------------------------

def dd_rate(folder, nbytes, reps):
    """Median MB/s of dd writing a file of nbytes (rounded up to MiB) with conv=fsync."""
    count = max(1, -(-nbytes // (1 << 20)))
    target = os.path.join(folder, "dd.tmp")
    rates = []
    for _ in range(reps):
        t0 = time.perf_counter()
        subprocess.run(["dd", "if=/dev/zero", f"of={target}", "bs=1M", f"count={count}", "conv=fsync"],
                       check=True, capture_output=True)
        rates.append(count * (1 << 20) / (time.perf_counter() - t0) / 1e6)
        os.remove(target)
    return statistics.median(rates)


def warm_page_pool(folder, mb):
    """Write and delete an mb-MiB file, so that the writes timed next get page-cache pages the
    kernel has just used. On this VM (virtio balloon/mem) memory touched for the first time in a
    while is several times slower to fill: the same 44 MB HDF5 write took 130-230 ms into fresh
    pages and 12-20 ms into recycled ones, which would make the first configuration timed look
    slow and dd (which recycles its own pages) look fast. Not needed on a real node."""
    if mb <= 0:
        return
    target = os.path.join(folder, "warm.tmp")
    subprocess.run(["dd", "if=/dev/zero", f"of={target}", "bs=1M", f"count={mb}"], check=True,
                   capture_output=True)
    os.remove(target)


def driver(args):
    env = dict(os.environ)
    env.setdefault("OMPI_MCA_rmaps_base_oversubscribe", "1")
    env.setdefault("OMPI_MCA_mpi_yield_when_idle", "1")
    if os.geteuid() == 0:
        env.update(OMPI_ALLOW_RUN_AS_ROOT="1", OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1")
    env["PYTHONPATH"] = REPO + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    rows = []
    for p in args.ranks:
        warm_page_pool(args.dir, args.warm_mb)
        cmd = ["mpirun", "-n", str(p), sys.executable, os.path.abspath(__file__), "--worker",
               "--n", str(args.n), "--reps", str(args.reps), "--dir", args.dir, "--dims"] + \
              [str(d) for d in args.dims] + (["--methods"] if args.methods and p == max(args.ranks) else [])
        proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=3600)
        if proc.returncode != 0:
            sys.exit(f"io_bench: {' '.join(cmd)} failed:\n{proc.stdout}\n{proc.stderr}")
        rows += [json.loads(l[4:]) for l in proc.stdout.splitlines() if l.startswith("ROW ")]
    report(args, rows)


def report(args, rows):
    dd = {}
    for r in rows:
        if r["bytes"] not in dd:
            dd[r["bytes"]] = dd_rate(args.dir, r["bytes"], args.reps)
    med = statistics.median
    print(f"N = {int(float(args.n)):.0e}, {args.reps} timed writes each (median, and best in brackets); "
          f"MB = 1e6 bytes; dd: bs=1M conv=fsync, same size, median of {args.reps}")
    print()
    print("| what | dim | ranks | MB | s incl. fsync | MB/s (page cache) | MB/s incl. fsync | dd MB/s | incl. fsync / dd |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        if r["kind"] == "snapshot" and r["method"] != "redistribute":
            continue
        mb = r["bytes"] / 1e6
        t, ts, d = r["seconds"], r["seconds_fsync"], dd[r["bytes"]]
        page = f"{mb / med(t):.0f} ({mb / min(t):.0f})" if r["kind"] == "snapshot" else "-"
        print(f"| {r['kind']} | {r['dim']} | {r['ranks']} | {mb:.1f} | {med(ts):.3f} | {page} | "
              f"{mb / med(ts):.0f} ({mb / min(ts):.0f}) | {d:.0f} | {mb / med(ts) / d:.2f} |")
    top = max(r["ranks"] for r in rows)
    meth = [r for r in rows if r["kind"] == "snapshot" and r["ranks"] == top]
    if len({r["method"] for r in meth}) > 1:
        print()
        print(f"snapshot rows into gid order, {top} ranks (seconds per snapshot, no fsync, median (best)):")
        for r in meth:
            print(f"  {r['dim']}D  {r['method']:<13} {med(r['seconds']):.3f} s ({min(r['seconds']):.3f} s)"
                  f"  {r['bytes'] / 1e6 / med(r['seconds']):.0f} MB/s")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", default="1e6")
    ap.add_argument("--dims", type=int, nargs="+", default=[2, 3])
    ap.add_argument("--ranks", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--dir", default=None, help="folder for the files (default: a temporary folder "
                    "in the current directory, removed afterwards)")
    ap.add_argument("--methods", action="store_true", help="also time the point-selection write")
    ap.add_argument("--warm-mb", type=int, default=2048, help="MiB written and deleted before each "
                    "rank count's writes (see warm_page_pool; 0: none)")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    under_mpirun = any(k in os.environ for k in ("OMPI_COMM_WORLD_SIZE", "PMI_SIZE"))
    if args.worker:
        worker(args)
        return
    made = args.dir is None
    if under_mpirun:
        # mpirun -n P python tools/io_bench.py: this rank count only; rank 0 runs dd and reports
        from mpi4py import MPI
        w = MPI.COMM_WORLD
        if made:
            args.dir = w.bcast(tempfile.mkdtemp(prefix="io_bench_", dir=os.getcwd())
                               if w.Get_rank() == 0 else None)
        try:
            if w.Get_rank() == 0:
                warm_page_pool(args.dir, args.warm_mb)
            w.Barrier()
            rows = worker(args)
            if rows is not None:
                report(args, rows)
        finally:
            w.Barrier()
            if made and w.Get_rank() == 0:
                shutil.rmtree(args.dir, ignore_errors=True)
        return
    if made:
        args.dir = tempfile.mkdtemp(prefix="io_bench_", dir=os.getcwd())
    try:
        driver(args)
    finally:
        if made:
            shutil.rmtree(args.dir, ignore_errors=True)


if __name__ == "__main__":
    main()
