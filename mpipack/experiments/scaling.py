"""Scaling past two cores, by counting: what each rank sends per iteration, and a model of
the time per iteration on K ranks built from those counts (issue 42).

A 2-core machine cannot time 32 ranks, but it can run them (oversubscribed) and count: the
traffic of a run is a function of the partition, not of the timing, because every decision
(rebuild, rebalance, stop) is taken from reduced values. Three commands:

    count   (under mpirun -n K) one scene for a fixed number of iterations with the
            communication counters on (``parallel.comm.Counts``); per iteration and per rank:
            messages and bytes by category, local and ghost particles, rebuilds. Appends one
            JSON line of per-rank figures per iterations (rank 0 writes).
    sweep   (serial) runs ``count`` for K = 2, 4, ..., 32, N, dimensions and starts, one
            mpirun at a time.
    model   reads the counts and ``mpipack bench`` rows (1 and 2 ranks) and predicts the time
            per iteration, speed-up and efficiency on 1 ... 1024 ranks, strong and weak; prints
            markdown tables and draws a figure.

    python -m mpipack.experiments.scaling sweep --json counts.jsonl
    python -m mpipack.experiments.scaling model --json counts.jsonl --bench bench.jsonl

The categories (``parallel.comm``): ``forward`` the ghost refresh of every iteration (point
to point), ``reduce`` the fused allreduce, ``check`` the exact-displacement allreduce when the
move bound trips, ``exchange`` the migration, ``borders`` the ghost copies, ``far`` far
pair-history partners (an allgather of requests and the copies again), ``rebuild`` the
rebuild's own collectives (the partition's bisection, load and memory checks), ``other``
everything else (hooks, the stop rule). Output and checkpoints move data through parallel
HDF5, not through these verbs, and are not counted.

The model (per iteration, on the slowest rank; all ranks wait for it at the allreduce):

    t_comp(K)  = t0 + n_max(K) c            n_max: the largest local count (imbalance)
    t_p2p      = messages L + bytes / B     forward, and the rebuild's point-to-point part
                                            amortised over the iterations between rebuilds
    t_allred   = ceil(log2 K) (L + payload / B) per call (recursive doubling)
    t_alltoall = (K - 1) L + bytes / B per call (pairwise exchange: an upper bound)
    t_allgath  = ceil(log2 K) L + K payload / B per call
    t_barrier  = ceil(log2 K) L per call (the alltoallv's non-blocking barrier)
    T(K)       = t_comp + t_comm;  speed-up S = T(1) / T(K), efficiency S / K

t0 and c come from ``mpipack bench`` (1 rank: c1 and t0 by a two-point fit over N; 2 ranks:
c2, the cost per particle-iteration with both cores busy, i.e. the memory bandwidth a core
gets when every core of a node works: used for K >= 2). Counts beyond K = 32 follow a
surface-to-volume law fitted to K = 2..32: per-rank ghosts and forward bytes
a (N/K)^((d-1)/d), messages per rank the largest measured value (a rank's neighbours in an
RCB partition saturate), the imbalance that of K = 32; each kind's latencies grow from the
largest measured K as its algorithm does (point to point: constant; an alltoall: K - 1; the
tree collectives and the barrier: log2 K).
"""

import argparse
import json
import math
import subprocess
import sys
import time

import numpy as np

# the benchmark's parameters (``experiments.bench``): the lattice stays put, every contact active
LATTICE = ["init.kind=lattice", "init.spacing=0.99", "method.form=S", "method.alpha=0.001",
           "method.beta=1.0", "method.gamma=0.001", "stop.eps=0"]

CATEGORIES = ("forward", "reduce", "check", "exchange", "borders", "far", "rebuild", "other")
REBUILD_CATEGORIES = ("exchange", "borders", "far", "rebuild")
NETWORKS = {  # name: (latency s, bandwidth bytes/s)
    "InfiniBand HDR-class (1.5 us, 12 GB/s)": (1.5e-6, 12e9),
    "10 GbE (20 us, 1.2 GB/s)": (20e-6, 1.2e9),
}
FIT_FROM_K = 8  # the surface-to-volume fits use K >= 8
KS_MODEL = [1, 2, 4, 8, 16, 32, 64, 128, 256, 512, 1024]


# ---- count: one run under mpirun ------------------------------------------------------------------
def scene_for(case, dim, n, iters, seed=1):
    from mpipack import config
    sets = [f"dim={dim}", f"n={n}", f"stop.max_iter={iters}", f"seed={seed}"]
    if case == "lattice":
        sets += LATTICE
    elif case != "gaussian":
        raise ValueError(f"case must be lattice or gaussian, not {case!r}")
    return config.load("default", sets)


def count_case(comm, case, dim, n, iters):
    """Run ``iters`` iterations of the case with the counters on. Returns, on rank 0, a dict
    of per-rank figures (lists over ranks), None elsewhere."""
    from mpipack.engine import hooks
    from mpipack.engine.loop import run
    from mpipack.parallel.comm import Counts

    scene = scene_for(case, dim, n, iters)
    counts = comm.count()
    rec = {"per_it": [], "rebuild_its": [], "ghosts": [], "local": []}
    last = {}

    def start(ctx):
        last["snap"] = counts.snapshot()
        last["rebuilds"] = ctx.solver.counters["rebuilds"]
        rec["setup"] = last["snap"]

    def every(ctx):
        snap = counts.snapshot()
        rec["per_it"].append(Counts.difference(snap, last["snap"]))
        st = ctx.solver.state
        rb = ctx.solver.counters["rebuilds"]
        rec["rebuild_its"].append(rb - last["rebuilds"])
        rec["ghosts"].append(st.n_total - st.n_local)
        rec["local"].append(st.n_local)
        last["snap"], last["rebuilds"] = snap, rb

    t0 = time.perf_counter()
    solver, res = run(scene, comm, hooks=[hooks.Hook(start, at_start=True), hooks.Hook(every, every=1)])
    seconds = time.perf_counter() - t0
    comm.count(False)
    mine = _summarise(rec, solver)
    allr = comm.mpi.gather(mine, root=0)
    if comm.rank != 0:
        return None
    out = {"case": case, "dim": dim, "n": n, "ranks": comm.size, "iterations": len(rec["per_it"]),
           "wall_seconds_oversubscribed": seconds}
    for key in allr[0]:
        out[key] = [r[key] for r in allr]
    return out


def _summarise(rec, solver):
    """One rank's figures over the counted iterations."""
    its = len(rec["per_it"])
    total = {}
    rebuild_total = {}
    for d, rb in zip(rec["per_it"], rec["rebuild_its"]):
        for c, kinds in d.items():
            for k, (m, b) in kinds.items():
                t = total.setdefault(f"{c}.{k}", [0, 0])
                t[0] += m
                t[1] += b
    n_rebuilds = int(sum(rec["rebuild_its"]))
    for d in rec["per_it"]:
        for c in REBUILD_CATEGORIES:
            for k, (m, b) in d.get(c, {}).items():
                t = rebuild_total.setdefault(f"{c}.{k}", [0, 0])
                t[0] += m
                t[1] += b
    setup = {f"{c}.{k}": list(v) for c, kinds in rec["setup"].items() for k, v in kinds.items()}
    return {
        "totals": total,  # "category.kind": [messages or calls, bytes] over the iterations
        "rebuilds": n_rebuilds,
        "setup": setup,
        "ghosts_mean": float(np.mean(rec["ghosts"])) if its else 0.0,
        "ghosts_max": int(np.max(rec["ghosts"])) if its else 0,
        "local_mean": float(np.mean(rec["local"])) if its else 0.0,
        "local_final": int(rec["local"][-1]) if its else 0,
        "far_ghosts": int(solver.counters["far_ghosts"]),
    }


# ---- sweep: the runs, one at a time ------------------------------------------------------------
def sweep(args):
    from mpipack.parallel.launcher import mpi_env
    runs = []
    for case in args.case:
        for dim in args.dim:
            for n in args.n:
                iters = args.iters if n <= 2e5 else args.iters_large
                for k in args.ranks:
                    runs.append((case, dim, int(n), iters, k))
    for case, dim, n, iters, k in runs:
        cmd = ["mpirun", "--oversubscribe", "-n", str(k), sys.executable, "-m", "mpipack.experiments.scaling",
               "count", "--case", case, "--dim", str(dim), "--n", str(n), "--iters", str(iters),
               "--json", args.json]
        t = time.perf_counter()
        proc = subprocess.run(cmd, env=mpi_env(), capture_output=True, text=True, timeout=args.timeout)
        print(f"{case:>8} {dim}D N={n:>8} K={k:>3} iters={iters}: exit {proc.returncode}, "
              f"{time.perf_counter() - t:.0f} s", flush=True)
        if proc.returncode != 0:
            print(proc.stdout[-2000:], proc.stderr[-2000:], file=sys.stderr)
    return 0


# ---- model ------------------------------------------------------------------------------------
def per_iteration(row):
    """Per-rank figures per iteration of one count row: {"category.kind": (n, bytes) arrays
    over ranks}, and the rebuild figures."""
    its = row["iterations"]
    keys = sorted({k for t in row["totals"] for k in t})
    out = {}
    for key in keys:
        m = np.array([t.get(key, [0, 0])[0] for t in row["totals"]], dtype=float) / its
        b = np.array([t.get(key, [0, 0])[1] for t in row["totals"]], dtype=float) / its
        out[key] = (m, b)
    return out


def load_rows(path):
    rows = {}
    with open(path) as f:
        for line in f:
            r = json.loads(line)
            rows[(r["case"], r["dim"], r["n"], r["ranks"])] = r  # the last run of a case wins
    return rows


def load_bench(path):
    """{(dim, ranks): {n: seconds per particle-iteration per rank}} from ``mpipack bench`` rows
    (the last row of each case wins)."""
    out = {}
    with open(path) as f:
        for line in f:
            r = json.loads(line)
            out.setdefault((r["dim"], r["ranks"]), {})[r["n"]] = 1.0 / r["rate_per_rank_median"]
    return out


def compute_law(bench, dim):
    """(t0, c1, c2): fixed seconds per iteration and seconds per particle-iteration, one rank
    (two-point fit t = t0 + n c over the bench's N) and with both cores busy (2 ranks, at the
    largest N, the fixed part subtracted)."""
    one = bench[(dim, 1)]
    ns = sorted(one)
    n_a, n_b = ns[0], ns[-1]
    t_a, t_b = n_a * one[n_a], n_b * one[n_b]
    c1 = (t_b - t_a) / (n_b - n_a)
    t0 = max(t_a - n_a * c1, 0.0)
    two = bench[(dim, 2)]
    nb2 = max(two)
    t_2 = (nb2 / 2) * two[nb2]  # seconds per iteration on 2 ranks: each holds nb2 / 2
    c2 = max(t_2 - t0, 0.0) / (nb2 / 2)
    return t0, c1, c2


def measured_table(rows, case, dim, n):
    """Per K: per-rank means and maxima per iteration of the counts (the table of the docs)."""
    table = []
    for k in sorted(kk for (c, d, nn, kk) in rows if (c, d, nn) == (case, dim, n)):
        row = rows[(case, dim, n, k)]
        pi = per_iteration(row)
        get = lambda key: pi.get(key, (np.zeros(k), np.zeros(k)))  # noqa: E731
        fwd_m, fwd_b = get("forward.p2p")
        red_c, red_b = get("reduce.allreduce")
        its = row["iterations"]
        reb_b = sum(np.array([t.get(f"{c}.{kind}", [0, 0])[1] for t in row["totals"]], float)
                    for c in REBUILD_CATEGORIES for kind in ("p2p", "alltoall", "allgather", "allreduce", "barrier"))
        reb_m = sum(np.array([t.get(f"{c}.p2p", [0, 0])[0] for t in row["totals"]], float)
                    for c in REBUILD_CATEGORIES)
        reb_coll = sum(np.array([t.get(f"{c}.{kind}", [0, 0])[0] for t in row["totals"]], float)
                       for c in REBUILD_CATEGORIES for kind in ("alltoall", "allgather", "allreduce", "barrier"))
        n_reb = max(row["rebuilds"])
        other_c = sum(pi[key][0] for key in pi if key.split(".")[0] in ("check", "other"))
        local = np.array(row["local_mean"])
        table.append({
            "K": k, "iterations": its, "rebuilds": n_reb,
            "fwd_msgs_mean": float(fwd_m.mean()), "fwd_msgs_max": float(fwd_m.max()),
            "fwd_bytes_mean": float(fwd_b.mean()), "fwd_bytes_max": float(fwd_b.max()),
            "reduce_calls": float(red_c.mean()), "reduce_bytes": float(red_b.mean()),
            "other_calls": float(np.mean(other_c)) if np.size(other_c) else 0.0,
            "rebuild_msgs_per_rebuild_mean": float(reb_m.mean() / n_reb) if n_reb else 0.0,
            "rebuild_bytes_per_rebuild_mean": float(reb_b.mean() / n_reb) if n_reb else 0.0,
            "rebuild_bytes_per_rebuild_max": float(reb_b.max() / n_reb) if n_reb else 0.0,
            "rebuild_colls_per_rebuild": float(reb_coll.mean() / n_reb) if n_reb else 0.0,
            "rebuild_bytes_per_it_mean": float(reb_b.mean() / its),
            "rebuild_msgs_per_it_mean": float(reb_m.mean() / its),
            "ghosts_mean": float(np.mean(row["ghosts_mean"])), "ghosts_max": float(np.max(row["ghosts_max"])),
            "imbalance": float(local.max() / local.mean()) if local.mean() > 0 else 1.0,
            "far_ghosts": int(max(row["far_ghosts"])),
            "_row": row,
        })
    return table


def _collective_seconds(kind, calls, payload, k, lat, bw):
    """Seconds of ``calls`` collectives of one kind with ``payload`` bytes (all calls) per rank."""
    if k <= 1 or calls == 0:
        return 0.0
    lg = math.ceil(math.log2(k))
    if kind == "allreduce":
        return calls * lg * lat + lg * payload / bw
    if kind == "alltoall":
        return calls * (k - 1) * lat + payload / bw
    if kind in ("allgather", "bcast", "gather"):
        return calls * lg * lat + k * payload / bw
    return calls * lg * lat  # barrier


def _growth(kind):
    """How a kind's latency grows with K: "const" (point to point: a rank's neighbours
    saturate), "linear" (an alltoall, K - 1 latencies), "log" (tree collectives)."""
    return "const" if kind == "p2p" else ("linear" if kind == "alltoall" else "log")


def iteration_comm(row, k, lat, bw, growth=None):
    """Seconds of communication per iteration on the slowest rank, by part, from one count row
    measured at k ranks. ``growth`` ("const", "linear" or "log"): only the kinds whose latency
    grows that way (``_growth``)."""
    its = row["iterations"]
    parts = {"forward": 0.0, "reductions": 0.0, "rebuild": 0.0}
    per_rank = np.zeros(k)
    by_part = {p: np.zeros(k) for p in parts}
    for r, tot in enumerate(row["totals"]):
        for key, (n, b) in tot.items():
            cat, kind = key.split(".")
            if growth is not None and _growth(kind) != growth:
                continue
            if kind == "p2p":
                sec = n * lat + b / bw
            else:
                sec = _collective_seconds(kind, n, b, k, lat, bw)
            part = "forward" if cat == "forward" else ("rebuild" if cat in REBUILD_CATEGORIES else "reductions")
            by_part[part][r] += sec / its
            per_rank[r] += sec / its
    worst = int(np.argmax(per_rank))
    return {p: float(v[worst]) for p, v in by_part.items()}


def fit_laws(rows, case, dim):
    """Surface-to-volume fits over every measured N and K = 2..32 of one case and dimension:
    forward bytes per rank per iteration (largest rank) = a_f (N/K)^((d-1)/d); rebuild bytes
    per rank per iteration likewise; messages per rank and per-iteration collective calls at the
    largest measured K."""
    pts = [(n, measured_table(rows, case, dim, n))
           for n in sorted({nn for (c, d, nn, kk) in rows if (c, d) == (case, dim)})]
    e = (dim - 1) / dim
    xs, fwd, reb, gh = [], [], [], []
    for n, table in pts:
        for t in table:
            if t["K"] < FIT_FROM_K:  # one or two cuts through the whole cloud: not yet the law
                continue
            xs.append((n / t["K"]) ** e)
            fwd.append(t["fwd_bytes_max"])
            reb.append(t["rebuild_bytes_per_it_mean"])
            gh.append(t["ghosts_max"])
    xs = np.array(xs)

    def fit(v):
        v = np.array(v, float)
        ok = v > 0
        if not ok.any():
            return 0.0, 0.0
        a = float(np.exp(np.mean(np.log(v[ok] / xs[ok]))))
        return a, float(np.sqrt(np.mean((v[ok] / (a * xs[ok]) - 1.0) ** 2)))

    # the exponent left free: log v = log a + p log(N/K), least squares (p = (d-1)/d if the law holds)
    v = np.array(fwd, float)
    ok = v > 0
    p_free = float(np.polyfit(np.log(xs[ok]) / e, np.log(v[ok]), 1)[0]) if ok.sum() >= 2 else math.nan
    return {"forward_bytes": fit(fwd), "rebuild_bytes": fit(reb), "ghosts": fit(gh), "points": len(xs),
            "free_exponent": p_free}


def predict(rows, bench, case, dim, n_total, lat, bw, weak=None):
    """Predicted seconds per iteration for K in KS_MODEL: measured counts where a run of that
    (N, K) exists, else the fitted laws. ``weak``: particles per rank (N = weak K)."""
    t0, c1, c2 = compute_law(bench, dim)
    law = fit_laws(rows, case, dim)
    ns = sorted({nn for (c, d, nn, kk) in rows if (c, d) == (case, dim)})
    e = (dim - 1) / dim
    out = []
    for k in KS_MODEL:
        n = weak * k if weak else n_total
        if k == 1:
            out.append({"K": 1, "comp": t0 + n * c1, "forward": 0.0, "reductions": 0.0, "rebuild": 0.0})
            continue
        key = (case, dim, n, k)
        if key in rows:
            row = rows[key]
            parts = iteration_comm(row, k, lat, bw)
            imb = max(row["local_mean"]) / (n / k)
            src = "measured"
        else:
            # the nearest measured N's largest K gives the messages, calls and imbalance
            n_ref = min(ns, key=lambda v: abs(math.log(v / n)))
            ks_ref = [kk for (c, d, nn, kk) in rows if (c, d, nn) == (case, dim, n_ref)]
            k_ref = k if k in ks_ref else max(ks_ref)  # the same K at another N, else the largest
            ref = rows[(case, dim, n_ref, k_ref)]
            p_ref = iteration_comm(ref, k_ref, 0.0, bw)  # the bytes' part only, at k_ref
            scale = (n / k) ** e / (n_ref / k_ref) ** e
            lg = math.ceil(math.log2(k)) / math.ceil(math.log2(k_ref))
            # the latency part, each kind grown from k_ref to k as its algorithm grows
            grow = {"const": 1.0, "linear": (k - 1) / (k_ref - 1), "log": lg}
            l_ref = {g: iteration_comm(ref, k_ref, lat, 1e300, growth=g) for g in grow}
            parts = {}
            for p in ("forward", "rebuild"):
                parts[p] = sum(l_ref[g][p] * f for g, f in grow.items()) + p_ref[p] * scale
            parts["reductions"] = sum(l_ref[g]["reductions"] * f for g, f in grow.items()) + p_ref["reductions"] * lg
            imb = max(ref["local_mean"]) / (n_ref / k_ref)
            src = "law"
        out.append({"K": k, "comp": t0 + imb * (n / k) * c2, **parts, "src": src})
    for o in out:
        o["comm"] = o["forward"] + o["reductions"] + o["rebuild"]
        o["T"] = o["comp"] + o["comm"]
    t1 = out[0]["T"]
    for o in out:
        if weak:
            o["speedup"] = o["K"] * t1 / o["T"]  # scaled speed-up: K times the work in T(K)
            o["efficiency"] = t1 / o["T"]
        else:
            o["speedup"] = t1 / o["T"]
            o["efficiency"] = o["speedup"] / o["K"]
    return out, law, (t0, c1, c2)


def half_point(pred):
    """The first K at which communication is more than half of the iteration (None: never up to
    1024)."""
    for o in pred:
        if o["comm"] > 0.5 * o["T"]:
            return o["K"]
    return None


def below_half(pred):
    """The first K at which the efficiency falls below 0.5 (None: never up to 1024)."""
    for o in pred:
        if o["efficiency"] < 0.5:
            return o["K"]
    return None


def model(args):
    rows = load_rows(args.json)
    bench = load_bench(args.bench)
    lines = []
    say = lines.append
    cases = sorted({c for (c, d, n, k) in rows})
    dims = sorted({d for (c, d, n, k) in rows})
    say("### Counts per iteration per rank\n")
    say("Means over ranks (max over ranks in brackets) per iteration; forward and rebuild are point-to-point "
        "messages and their bytes; the reduction is one fused allreduce (calls, payload per rank); rebuild "
        "traffic (exchange + borders + far + the rebuild's collectives) per rebuild and amortised per "
        "iteration; ghosts and the imbalance (largest local count / mean) over the counted iterations.\n")
    say("| start | dim | N | K | iters | fwd msgs | fwd bytes | allreduce calls, B | other colls | "
        "rebuilds | rebuild msgs / rebuild | rebuild kB / rebuild | rebuild colls / rebuild | "
        "rebuild B / it | ghosts / rank | imbalance | far |")
    say("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for case in cases:
        for dim in dims:
            for n in sorted({nn for (c, d, nn, kk) in rows if (c, d) == (case, dim)}):
                for t in measured_table(rows, case, dim, n):
                    say(f"| {case} | {dim} | {n:.0e} | {t['K']} | {t['iterations']} | "
                        f"{t['fwd_msgs_mean']:.1f} ({t['fwd_msgs_max']:.0f}) | "
                        f"{t['fwd_bytes_mean']:.0f} ({t['fwd_bytes_max']:.0f}) | "
                        f"{t['reduce_calls']:.2f}, {t['reduce_bytes']:.0f} | {t['other_calls']:.2f} | {t['rebuilds']} | "
                        f"{t['rebuild_msgs_per_rebuild_mean']:.0f} | "
                        f"{t['rebuild_bytes_per_rebuild_mean'] / 1e3:.0f} ({t['rebuild_bytes_per_rebuild_max'] / 1e3:.0f}) | "
                        f"{t['rebuild_colls_per_rebuild']:.0f} | {t['rebuild_bytes_per_it_mean']:.0f} | "
                        f"{t['ghosts_mean']:.0f} ({t['ghosts_max']:.0f}) | {t['imbalance']:.3f} | {t['far_ghosts']} |")
    say("")
    say(f"### Surface-to-volume fits (K = {FIT_FROM_K}..32, every N)\n")
    say("| start | dim | forward bytes / rank / it (largest rank) | rms rel. residual | free exponent | ghosts / rank (largest) | rms | rebuild bytes / rank / it | rms | points |")
    say("|---|---|---|---|---|---|---|---|---|---|")
    for case in cases:
        for dim in dims:
            if not any((c, d) == (case, dim) for (c, d, n, k) in rows):
                continue
            law = fit_laws(rows, case, dim)
            e = f"(N/K)^{dim - 1}/{dim}"
            f, g, r = law["forward_bytes"], law["ghosts"], law["rebuild_bytes"]
            say(f"| {case} | {dim} | {f[0]:.1f} {e} | {f[1]:.2f} | {law['free_exponent']:.2f} | {g[0]:.2f} {e} | {g[1]:.2f} | "
                f"{r[0]:.2f} {e} | {r[1]:.2f} | {law['points']} |")
    say("")
    say("### Compute law from `mpipack bench` on this machine\n")
    say("| dim | t0 (fixed s / iteration) | c1 (ns / particle-it, 1 rank) | c2 (ns / particle-it, 2 ranks busy) |")
    say("|---|---|---|---|")
    for dim in dims:
        t0, c1, c2 = compute_law(bench, dim)
        say(f"| {dim} | {t0 * 1e6:.0f} us | {c1 * 1e9:.1f} | {c2 * 1e9:.1f} |")
    say("")
    figure_data = []
    for net, (lat, bw) in NETWORKS.items():
        say(f"### Predictions, {net}\n")
        say("Speed-up (efficiency); * where communication is more than half of an iteration.\n")
        say("| start | dim | scaling | " + " | ".join(f"K={k}" for k in KS_MODEL[1:]) + " | comm > half at K | efficiency < 0.5 at K |")
        say("|---|---|---|" + "---|" * (len(KS_MODEL) - 1) + "---|---|")
        for case in cases:
            for dim in dims:
                ns = sorted({nn for (c, d, nn, kk) in rows if (c, d) == (case, dim)})
                if not ns:
                    continue
                sets = [(f"strong N={n:.0e}", dict(n_total=n)) for n in ns]
                if 100000 in ns:
                    sets.append(("weak 1e5/rank", dict(n_total=None, weak=100000)))
                for label, kw in sets:
                    pred, _, _ = predict(rows, bench, case, dim, lat=lat, bw=bw, **kw)
                    hp, bh = half_point(pred), below_half(pred)
                    cells = []
                    for o in pred[1:]:
                        flag = "*" if o["comm"] > 0.5 * o["T"] else ""
                        cells.append(f"{o['speedup']:.3g} ({o['efficiency']:.2f}){flag}")
                    say(f"| {case} | {dim} | {label} | " + " | ".join(cells) + f" | {hp if hp else '> 1024'} | {bh if bh else '> 1024'} |")
                    figure_data.append((net, case, dim, label, pred))
        say("")
        say(f"Where the time of an iteration goes ({net}), microseconds on the slowest rank: "
            "fixed per-iteration cost t0 + particles + forward + reductions + rebuilds (amortised)\n")
        say("| start | dim | scaling | K=32 | K=256 | K=1024 |")
        say("|---|---|---|---|---|---|")
        for (nn, case, dim, label, pred) in figure_data:
            if nn != net:
                continue
            t0 = compute_law(bench, dim)[0]
            cells = [f"{t0 * 1e6:.0f} + {(o['comp'] - t0) * 1e6:.0f} + {o['forward'] * 1e6:.0f} + "
                     f"{o['reductions'] * 1e6:.0f} + {o['rebuild'] * 1e6:.0f}"
                     for o in pred if o["K"] in (32, 256, 1024)]
            say(f"| {case} | {dim} | {label} | " + " | ".join(cells) + " |")
        say("")
    say("(* communication more than half of the iteration.)")
    text = "\n".join(lines)
    print(text)
    if args.md:
        with open(args.md, "w") as f:
            f.write(text + "\n")
    if args.figure:
        draw(figure_data, args.figure)
    return 0


def draw(figure_data, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    nets = list(NETWORKS)
    fig, axes = plt.subplots(1, len(nets), figsize=(6 * len(nets), 4.5), sharey=True)
    for ax, net in zip(np.atleast_1d(axes), nets):
        for (nn, case, dim, label, pred) in figure_data:
            if nn != net or case != "lattice":
                continue
            ks = [o["K"] for o in pred]
            ax.plot(ks, [o["efficiency"] for o in pred], marker="o", ms=3,
                    ls="-" if "strong" in label else "--", label=f"{dim}D {label}")
        ax.set_xscale("log", base=2)
        ax.set_ylim(0, 1.1)
        ax.axhline(0.5, color="grey", lw=0.5)
        ax.set_xlabel("ranks K")
        ax.set_title(net, fontsize=10)
        ax.grid(alpha=0.3)
    np.atleast_1d(axes)[0].set_ylabel("predicted parallel efficiency")
    np.atleast_1d(axes)[0].legend(fontsize=7)
    fig.suptitle("mpipack: predicted efficiency from counted traffic (lattice start, every contact active)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main(argv=None):
    p = argparse.ArgumentParser(prog="python -m mpipack.experiments.scaling", description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="command", required=True)
    c = sub.add_parser("count", help="one case with the counters on (under mpirun -n K)")
    c.add_argument("--case", default="lattice", choices=["lattice", "gaussian"])
    c.add_argument("--dim", type=int, default=2)
    c.add_argument("--n", type=float, default=1e5)
    c.add_argument("--iters", type=int, default=200)
    c.add_argument("--json", default=None, help="append the per-rank figures to this JSON-lines file")
    s = sub.add_parser("sweep", help="count every case on K = 2..32 ranks, one mpirun at a time")
    s.add_argument("--case", action="append", default=None, choices=["lattice", "gaussian"])
    s.add_argument("--dim", type=int, action="append", default=None)
    s.add_argument("--n", type=float, action="append", default=None)
    s.add_argument("--ranks", type=int, action="append", default=None)
    s.add_argument("--iters", type=int, default=200, help="iterations at N <= 2e5")
    s.add_argument("--iters-large", type=int, default=30, help="iterations at larger N")
    s.add_argument("--timeout", type=float, default=1800)
    s.add_argument("--json", required=True)
    m = sub.add_parser("model", help="tables and a figure from the counts and the bench rows")
    m.add_argument("--json", required=True, help="the counts (sweep's file)")
    m.add_argument("--bench", required=True, help="`mpipack bench --json` rows, 1 and 2 ranks")
    m.add_argument("--md", default=None, help="write the tables here too")
    m.add_argument("--figure", default=None, help="a PNG of the predicted efficiencies")
    args = p.parse_args(argv)
    if args.command == "count":
        from mpipack.parallel.comm import Comm
        comm = Comm()
        out = count_case(comm, args.case, args.dim, int(args.n), args.iters)
        if out is not None:
            line = json.dumps(out)
            if args.json:
                with open(args.json, "a") as f:
                    f.write(line + "\n")
            fwd = [t.get("forward.p2p", [0, 0]) for t in out["totals"]]
            print(f"{args.case} {args.dim}D N={int(args.n)} K={comm.size}: {out['iterations']} iterations, "
                  f"forward messages per rank {[m for m, _ in fwd]}, bytes {[b for _, b in fwd]}, "
                  f"rebuilds {max(out['rebuilds'])}", flush=True)
        return 0
    if args.command == "sweep":
        args.case = args.case or ["lattice", "gaussian"]
        args.dim = args.dim or [2, 3]
        args.n = args.n or [1e5, 1e6]
        args.ranks = args.ranks or [2, 4, 8, 16, 32]
        return sweep(args)
    return model(args)


if __name__ == "__main__":
    sys.exit(main())
