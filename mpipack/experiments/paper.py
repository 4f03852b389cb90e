"""``mpipack paper``: re-run the paper's experiments, write a markdown report and PNG figures.

Small experiments (N = 7 and N = 100) are many independent runs: they are dealt out to the
ranks (each runs its share on its own, on MPI.COMM_SELF) and gathered on rank 0. The
N = 2000 cases run on all ranks together.

Counting T: for DAHA and AHA an iteration is one step; for NAP and NAV the paper's Table 1
is reproduced when T counts inner iterations (all the inner steps of all outer iterations),
so that is the T reported (outer counts are reported beside it). Fig. 5 and 6 use the same
count on their horizontal axis.
"""

import math
import os
import time

import numpy as np

from mpipack import post

# Paper, Table 1 (N = 7, 20 standard Gaussian starts): T, sigma^2, orders of (A, W - 3)
EPS_T1 = ((1e-4, 1e-7), (1e-6, 1e-9), (1e-8, 1e-11))
PAPER_T = {"DAHA-NS": (103, 145, 198), "DAHA-S": (85, 133, 182), "NAP-NS": (81, 107, 131),
           "NAP-S": (165, 246, 325), "NAV-NS": (248, 283, 535)}
PAPER_VAR = {"DAHA-NS": (1.08e3, 1.21e3, 1.70e3), "DAHA-S": (4.19e2, 4.49e2, 5.65e2),
             "NAP-NS": (3.00e2, 4.13e2, 2.93e2), "NAP-S": (5.74e2, 4.68e2, 4.68e2),
             "NAV-NS": (1.03e4, 1.04e4, 1.80e5)}
PAPER_A = {"DAHA-NS": (1e-6, 1e-9, 1e-12), "DAHA-S": (1e-7, 1e-10, 1e-12), "NAP-NS": (1e-9, 1e-12, 1e-15),
           "NAP-S": (1e-8, 1e-11, 1e-13), "NAV-NS": (1e-8, 1e-10, 1e-14)}
PAPER_W = {"DAHA-NS": (-1e-6, -1e-9, -1e-13), "DAHA-S": (-1e-6, -1e-10, -1e-13), "NAP-NS": (1e-8, 1e-12, 0.0),
           "NAP-S": (-1e-5, 1e-6, -1e-8), "NAV-NS": (1e-1, -1e-1, 1e-9)}
# Table 1 caption parameters; Fig. 6 caption parameters (N = 100)
T1_PARAMS = {
    "DAHA-NS": dict(name="daha", form="NS", alpha=0.3, beta=3.0, c=2.0),
    "DAHA-S": dict(name="daha", form="S", alpha=0.35, beta=1.4, c=2.0),
    "NAP-NS": dict(name="nap", form="NS", alpha=0.6, beta=0.46, l_inner=10),
    "NAP-S": dict(name="nap", form="S", alpha=0.25, beta=0.28, l_inner=10),
    "NAV-NS": dict(name="nav", form="NS", alpha=0.48, beta=126.0, l_inner=10, tau=0.1),
}
F6_PARAMS = {
    "DAHA-NS": dict(name="daha", form="NS", alpha=0.07, beta=0.5, c=2.0),
    "DAHA-S": dict(name="daha", form="S", alpha=0.04, beta=0.15, c=2.0),
    "NAP-NS": dict(name="nap", form="NS", alpha=0.1, beta=0.16, l_inner=1000),
    "NAP-S": dict(name="nap", form="S", alpha=0.015, beta=0.026, l_inner=1000),
    "NAV-NS": dict(name="nav", form="NS", alpha=0.31, beta=41.0, l_inner=1000, tau=0.1),
}
# Table 2 of the paper: simulations column (2D), per method and form
PAPER_T2 = {("AHA", "S"): False, ("AHA", "NS"): False, ("DAHA", "S"): True, ("DAHA", "NS"): True,
            ("NAP", "S"): True, ("NAP", "NS"): True, ("NAV", "S"): False, ("NAV", "NS"): True}


def scene_for(n, dim, seed, params, eps, eps_inner=1e-9, max_iter=100000, extra=()):
    """A validated scene dict: N spheres, standard Gaussian start, the given method params."""
    from .. import config
    sets = [f"n={n}", f"dim={dim}", "init.sigma=1.0", "stop.rule=eps", f"stop.eps={eps}", f"stop.max_iter={max_iter}",
            f"method.eps_inner={eps_inner}", "output.progress_every=0", "stop.watchdog=false"]
    for k, v in params.items():
        sets.append(f"method.{k}={v}" if k != "name" and k != "form" else f"method.{k}=\"{v}\"")
    if params.get("name") in ("daha", "aha") and "gamma" not in params:
        sets.append(f"method.gamma={math.sqrt(params['alpha'] * params['beta'])}")
    return config.load("paper-2d", list(sets) + list(extra), seed=seed)


def overlap_area_sum(x, d=1.0):
    """Sum over pairs i<j of the overlap area of discs of diameter d (2D)."""
    a = 0.5 * d
    diff = x[:, None, :] - x[None, :, :]
    r = np.sqrt((diff ** 2).sum(-1))
    iu = np.triu_indices(x.shape[0], 1)
    r = r[iu]
    r = r[r < d]
    return float(np.sum(2 * a * a * np.arccos(r / (2 * a)) - 0.5 * r * np.sqrt(np.maximum(4 * a * a - r * r, 0))))


def run_single(scene, budget=None, trace=False, comm=None):
    """Run one scene to its stopping test (or ``budget`` work units: iterations for one-pass
    methods, inner iterations for nested ones). Returns a dict of results."""
    from mpipack.engine import hooks, loop, solver as solver_mod
    from mpipack.errors import NumericalError
    from mpipack.parallel.comm import Comm
    comm = comm or Comm.serial()
    s = solver_mod.Solver(scene, comm)
    s.initialise()
    eps = scene.stop.eps
    errs, work_axis = [], []

    def work():
        return s.counters["inner_iterations"] if s.method.counts_inner else s.state.iteration

    def record(ctx):
        errs.append(ctx.figures["relative_change"])
        work_axis.append(work())

    def budget_spent(ctx):
        # (4.3) wins when it fires on the same iteration
        if eps > 0 and ctx.figures["relative_change"] < eps:
            return None
        return hooks.STOP if work() >= budget else None

    hook_list = ([hooks.Hook(record, every=1)] if trace else []) + \
        ([hooks.Hook(budget_spent, every=1, name="budget")] if budget is not None else [])
    t0 = time.perf_counter()
    try:
        _, res = loop.run(scene, comm, hooks=hook_list, solver=s)
        status = "ok"
    except NumericalError:
        res = {"converged": False, "W": math.nan, "max_overlap": math.nan,
               "relative_change": errs[-1] if errs else math.nan}
        status = "diverged"
    wall = time.perf_counter() - t0
    g = s.gather()
    # the paper's notion: its stopping criterion (4.3) fired (the certificate is not asked for)
    out = {"converged": res.get("stop_reason") == "eps", "status": status, "outer": s.state.iteration,
           "inner": s.counters["inner_iterations"],
           "T": s.counters["inner_iterations"] if s.method.counts_inner else s.state.iteration,
           "W": res["W"], "max_overlap": res["max_overlap"], "wall": wall,
           "relative_change": res["relative_change"]}
    if g is not None and scene.dim == 2 and scene.n <= 200 and status == "ok":
        out["overlap_area"] = overlap_area_sum(g["x"])
    if trace:
        out["trace"] = (work_axis, errs)
    return out


def distribute(comm, tasks, fn):
    """Run fn(task) for tasks dealt round-robin over ranks; the results in task order, on all ranks."""
    mine = [(i, fn(t)) for i, t in enumerate(tasks) if i % comm.size == comm.rank]
    parts = comm.allgather_object(mine)
    res = [None] * len(tasks)
    for part in parts:
        for i, r in part:
            res[i] = r
    return res


# ---- experiments -------------------------------------------------------------------------------
def table1(comm, seed_sets):
    """Table 1 over len(seed_sets) disjoint sets of seeds. Returns per method/eps statistics."""
    tasks = [(name, k, sset, seed) for name in T1_PARAMS for k in range(3)
             for sset in range(len(seed_sets)) for seed in seed_sets[sset]]

    def fn(t):
        name, k, sset, seed = t
        eps, ei = EPS_T1[k]
        r = run_single(scene_for(7, 2, seed, T1_PARAMS[name], eps, ei, max_iter=20000))
        return {"T": r["T"], "outer": r["outer"], "W": r["W"], "A": r.get("overlap_area", math.nan),
                "conv": r["converged"], "ov": r["max_overlap"]}

    res = distribute(comm, tasks, fn)
    out = {}
    for (name, k, sset, seed), r in zip(tasks, res):
        out.setdefault((name, k), {}).setdefault(sset, []).append(r)
    stats = {}
    a_total = 7 * math.pi * 0.25
    for (name, k), sets in out.items():
        first = sets[0]
        T = np.array([r["T"] for r in first], float)
        set_means = [np.mean([r["T"] for r in s]) for s in sets.values()]
        stats[(name, k)] = {
            "T": float(T.mean()), "var": float(T.var(ddof=1)) if len(T) > 1 else 0.0,
            "outer": float(np.mean([r["outer"] for r in first])),
            "A": float(np.sum([r["A"] for r in first]) / (len(first) * 7 * a_total)),
            "W3": float(np.mean([r["W"] - 3.0 for r in first])),
            "W3_median": float(np.median([r["W"] - 3.0 for r in first])),
            # starts that stopped away from the optimum (another local minimum of W)
            "n_off": int(sum(abs(r["W"] - 3.0) > 1e-3 for r in first)),
            "W3_opt": float(np.mean([r["W"] - 3.0 for r in first if abs(r["W"] - 3.0) <= 1e-3] or [math.nan])),
            "conv": int(sum(r["conv"] for r in first)), "m": len(first),
            "spread": (float(min(set_means)), float(max(set_means))),
            "max_ov": float(np.nanmax([r["ov"] for r in first])),
        }
    return stats


def is_valid_packing(r, n):
    """Converged, and really a packing: max overlap below 1e-3 d and W within 1e-3 of the
    optimum 3 for N = 7; max overlap below 1e-2 d for larger N (at eps = 1e-6 a converging
    N = 100 run still overlaps by up to about 1e-3 d; a wrong stop overlaps by far more)."""
    tol = 1e-3 if n == 7 else 1e-2
    if not r["converged"] or r["status"] != "ok" or not (r["max_overlap"] < tol):
        return False
    return abs(r["W"] - 3.0) < 1e-3 if n == 7 else True


T2_BUDGET = {7: 20000, 100: 40000}  # iterations (inner iterations for NAP/NAV) per start
T2_SEARCH = {"alpha": (0.02, 0.1, 0.3), "beta": (0.1, 1.0, 3.0)}


def table2(comm, quick):
    """For each method and form, does it converge to a valid packing in 2D for N = 7 and 100."""
    rows = []
    budget = T2_BUDGET if not quick else {7: 20000, 100: 4000}
    seeds = {7: range(1, 6 if quick else 11), 100: range(1, 3 if quick else 4)}
    base = {
        ("AHA", "S"): dict(name="aha", form="S", alpha=0.01, beta=0.01),
        ("AHA", "NS"): dict(name="aha", form="NS", alpha=0.3, beta=3.0),
        ("NAV", "S"): dict(name="nav", form="S", alpha=0.48, beta=126.0, l_inner=10, tau=0.1),
    }
    tasks = []
    for (meth, form), paper in PAPER_T2.items():
        key = f"{meth}-{form}"
        for n in (7, 100):
            if (meth, form) in base:
                p = dict(base[(meth, form)])
                if n == 100 and meth == "NAV":
                    p["l_inner"] = 1000
            else:
                p = dict((T1_PARAMS if n == 7 else F6_PARAMS)[key])
            cands = [("caption", p)]
            if not (quick and n == 100):
                for a in T2_SEARCH["alpha"]:
                    for b in T2_SEARCH["beta"]:
                        q = dict(p, alpha=a, beta=b)
                        cands.append((f"alpha={a}, beta={b}", q))
            tasks.append((meth, form, n, cands))

    def fn(t):
        meth, form, n, cands = t
        tried = []
        for label, p in cands:
            rs = []
            for seed in seeds[n]:  # a parameter set fails at its first failing start
                rs.append(run_single(scene_for(n, 2, seed, p, 1e-6, 1e-9, max_iter=budget[n]),
                                     budget=budget[n]))
                if not is_valid_packing(rs[-1], n):
                    break
            ok = len(rs) == len(seeds[n]) and all(is_valid_packing(r, n) for r in rs)
            fired = sum(r["converged"] for r in rs)
            tried.append({"label": label, "ok": ok, "fired": fired, "runs": len(rs),
                          "diverged": sum(r["status"] == "diverged" for r in rs),
                          "max_ov": float(max((r["max_overlap"] for r in rs if r["status"] == "ok"),
                                              default=math.nan)),
                          "T": float(np.mean([r["T"] for r in rs]))})
            if ok:
                break
            if quick:
                break
        return tried

    res = distribute(comm, tasks, fn)
    for (meth, form, n, _), tried in zip(tasks, res):
        rows.append({"method": meth, "form": form, "n": n, "paper": PAPER_T2[(meth, form)],
                     "ours": any(t["ok"] for t in tried), "tried": tried})
    return rows


def traces(comm, n, params_by_name, seeds, eps, budget, extra=()):
    tasks = [(name, seed) for name in params_by_name for seed in seeds]

    def fn(t):
        name, seed = t
        r = run_single(scene_for(n, 2, seed, params_by_name[name], eps, 1e-9, max_iter=budget, extra=extra),
                       budget=budget, trace=True)
        return {"trace": r["trace"], "T": r["T"], "conv": r["converged"]}

    res = distribute(comm, tasks, fn)
    out = {}
    for (name, seed), r in zip(tasks, res):
        out.setdefault(name, []).append(r)
    return out


def fig3_data(comm, cs, seeds):
    tasks = [(form, c, seed) for form in ("NS", "S") for c in cs for seed in seeds]
    params = {"NS": dict(name="daha", form="NS", alpha=0.3, beta=3.0),
              "S": dict(name="daha", form="S", alpha=0.3, beta=1.4)}

    def fn(t):
        form, c, seed = t
        r = run_single(scene_for(7, 2, seed, dict(params[form], c=c), 1e-6, max_iter=5000))
        return r["T"] if r["converged"] else 5000

    res = distribute(comm, tasks, fn)
    out = {}
    for (form, c, seed), T in zip(tasks, res):
        out.setdefault(form, {}).setdefault(c, []).append(T)
    return {f: (list(d), [max(v) for v in d.values()]) for f, d in out.items()}


def fig4_data(comm, cs, seeds, iters):
    params = {"NS": dict(name="daha", form="NS", alpha=0.3, beta=3.0),
              "S": dict(name="daha", form="S", alpha=0.35, beta=1.4)}
    tasks = [(form, c, seed) for form in ("NS", "S") for c in cs for seed in seeds]

    def fn(t):
        form, c, seed = t
        r = run_single(scene_for(7, 2, seed, dict(params[form], c=c), 0.0, max_iter=iters), trace=True)
        return np.log10(np.maximum(np.array(r["trace"][1]), 1e-17))

    res = distribute(comm, tasks, fn)
    out = {}
    for (form, c, seed), tr in zip(tasks, res):
        out.setdefault(form, {}).setdefault(c, []).append(tr)
    return {f: {c: np.mean(np.stack(v), axis=0) for c, v in d.items()} for f, d in out.items()}


def large_2d(comm, quick, extra_iters):
    """Section 4.3: N = 2000 DAHA-S to eps = 1e-5, then extra_iters more iterations."""
    from mpipack import config
    from mpipack.engine import loop
    scene = config.load("paper-2d", ["output.progress_every=0", "stop.watchdog=false"] + (["n=500"] if quick else []))
    t0 = time.perf_counter()
    s, first = loop.run(scene, comm)
    fired_at = s.state.iteration
    wall = time.perf_counter() - t0
    g1 = s.gather()
    _, later = loop.run(scene.replace(stop={"eps": 0.0, "max_iter": fired_at + extra_iters}),
                              comm, solver=s)
    g2 = s.gather()
    return {"n": scene.n, "fired_at": fired_at, "wall": wall, "first": (first, g1),
            "later": (later, g2), "extra": extra_iters}


def large_3d(comm, quick):
    from mpipack import config
    from mpipack.engine import loop
    scene = config.load("paper-3d", ["output.progress_every=0", "stop.watchdog=false"]
                        + (["n=500", "stop.max_iter=2000"] if quick else []))
    t0 = time.perf_counter()
    s, f = loop.run(scene, comm)
    return {"n": scene.n, "iters": s.state.iteration, "wall": time.perf_counter() - t0,
            "final": f, "g": s.gather()}


# ---- report -------------------------------------------------------------------------------------
def _fmt_order(v):
    if v == 0 or not np.isfinite(v):
        return f"{v:.0f}" if v == 0 else "nan"
    return f"{'-' if v < 0 else ''}1e{int(math.floor(math.log10(abs(v)) + 1e-9))}"


def _plots(out, f3, f4, f5, f6, l2, l3, prof2, prof3, radii2, radii3, counts3):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    files = {}
    fig, axs = plt.subplots(1, 2, figsize=(10, 4))
    for ax, form, title in ((axs[0], "NS", "(a) DAHA-NS (0.3, 3)"), (axs[1], "S", "(b) DAHA-S (0.3, 1.4)")):
        cs, mx = f3[form]
        ax.semilogy(cs, mx, "o-")
        ax.set_xlabel("damping c")
        ax.set_ylabel("max iterations over starts (eps 1e-6)")
        ax.set_title(title)
    fig.tight_layout()
    files["fig3"] = "fig3_iterations_vs_c.png"
    fig.savefig(os.path.join(out, files["fig3"]), dpi=90)
    plt.close(fig)
    fig, axs = plt.subplots(1, 2, figsize=(10, 4))
    for ax, form, title in ((axs[0], "NS", "(a) DAHA-NS (0.3, 3)"), (axs[1], "S", "(b) DAHA-S (0.35, 1.4)")):
        for c, tr in f4[form].items():
            ax.plot(np.arange(1, len(tr) + 1), tr, label=f"c = {c:g}")
        ax.set_xlabel("iteration n")
        ax.set_ylabel("mean log10 relative change")
        ax.set_title(title)
        ax.legend(fontsize=7)
    fig.tight_layout()
    files["fig4"] = "fig4_error_vs_iteration_c.png"
    fig.savefig(os.path.join(out, files["fig4"]), dpi=90)
    plt.close(fig)
    for key, data, title in (("fig5", f5, "N = 7"), ("fig6", f6, "N = 100")):
        names = list(data)
        fig, axs = plt.subplots(1, len(names), figsize=(3.2 * len(names), 3.2), sharey=True)
        for ax, name in zip(np.atleast_1d(axs), names):
            for r in data[name]:
                w, e = r["trace"]
                ax.plot(w, np.log10(np.maximum(e, 1e-17)), lw=0.8)
            ax.set_title(name, fontsize=9)
            ax.set_xlabel("iterations (inner for NAP/NAV)", fontsize=8)
        np.atleast_1d(axs)[0].set_ylabel("log10 relative change")
        fig.suptitle(f"relative change vs iterations, {title}")
        fig.tight_layout()
        files[key] = f"{key}_error_vs_iteration.png"
        fig.savefig(os.path.join(out, files[key]), dpi=90)
        plt.close(fig)
    fig, axs = plt.subplots(1, 3, figsize=(13, 4))
    x = l2["first"][1]["x"]
    axs[0].scatter(x[:, 0], x[:, 1], s=2)
    axs[0].set_aspect("equal")
    axs[0].set_title(f"2D N = {l2['n']} when (4.3) fired")
    axs[1].plot(radii2, prof2, label=f"2D N = {l2['n']}")
    axs[1].plot(radii3, prof3, label=f"3D N = {l3['n']}")
    axs[1].axhline(0.87, ls=":", c="C0")
    axs[1].axhline(0.65, ls=":", c="C1")
    axs[1].set_xlabel("R")
    axs[1].set_ylabel("packing density phi(R)")
    axs[1].legend()
    axs[2].hist(counts3, bins=np.arange(-0.5, 15.5, 1))
    axs[2].set_xlabel("neighbours within 1.1 d (3D)")
    fig.tight_layout()
    files["fig8_10"] = "fig8_fig10_density_neighbours.png"
    fig.savefig(os.path.join(out, files["fig8_10"]), dpi=90)
    plt.close(fig)
    return files


def main(args):
    from mpipack.parallel.comm import Comm
    comm = Comm()
    quick = args.quick
    out = args.out or os.path.join("mpipack-out", "paper-quick" if quick else "paper")
    if comm.rank == 0:
        os.makedirs(out, exist_ok=True)
    t_start = time.perf_counter()
    timing = {}

    def lap(name, t):
        timing[name] = time.perf_counter() - t
        if comm.rank == 0:
            print(f"mpipack paper: {name} done in {timing[name]:.1f} s", flush=True)

    if quick:
        seed_sets = [list(range(1, 6))]
    else:
        seed_sets = [list(range(1 + 20 * k, 21 + 20 * k)) for k in range(10)]
    t = time.perf_counter()
    t1 = table1(comm, seed_sets)
    lap("table1", t)
    t = time.perf_counter()
    t2 = table2(comm, quick)
    lap("table2", t)
    t = time.perf_counter()
    cs3 = [0.5, 1, 2, 4] if quick else [0.25 * k for k in range(1, 41)]
    f3 = fig3_data(comm, cs3, range(1, 4) if quick else range(1, 21))
    cs4 = [0.1, 0.5, 2.0] if quick else [0.1, 0.5, 1.0, 2.0, 4.0, 8.0]
    f4 = fig4_data(comm, cs4, range(1, 4) if quick else range(1, 21), 150 if quick else 400)
    f5 = traces(comm, 7, T1_PARAMS, range(1, 4) if quick else range(1, 21), 1e-6, 20000)
    f6 = traces(comm, 100, F6_PARAMS, range(1, 2) if quick else range(1, 6), 1e-6, 3000 if quick else 30000)
    lap("figures 3-6", t)
    t = time.perf_counter()
    l2 = large_2d(comm, quick, 500 if quick else 3000)
    l3 = large_3d(comm, quick)
    lap("N = 2000", t)
    if comm.rank == 0:
        g2 = l2["first"][1]
        g2b = l2["later"][1]
        rmax2 = float(np.sqrt(((g2["x"] - g2["x"].mean(0)) ** 2).sum(1)).max())
        radii2 = np.linspace(1.0, rmax2, 60)
        prof2 = post.density_profile(g2["x"], g2["diam"], radii2)
        prof2b = post.density_profile(g2b["x"], g2b["diam"], radii2)
        g3 = l3["g"]
        rmax3 = float(np.sqrt(((g3["x"] - g3["x"].mean(0)) ** 2).sum(1)).max())
        radii3 = np.linspace(1.0, rmax3, 60)
        prof3 = post.density_profile(g3["x"], g3["diam"], radii3)
        counts3 = post.neighbour_counts(g3["x"], g3["diam"])
        files = _plots(out, f3, f4, f5, f6, l2, l3, prof2, prof3, radii2, radii3, counts3)
        timing["total"] = time.perf_counter() - t_start
        text = _report(comm, quick, t1, t2, f3, f5, f6, l2, l3, radii2, prof2, prof2b, radii3, prof3,
                       counts3, files, timing)
        with open(os.path.join(out, "report.md"), "w") as f:
            f.write(text)
        print(f"mpipack paper: report written to {os.path.join(out, 'report.md')} "
              f"in {timing['total']:.1f} s on {comm.size} rank(s)", flush=True)
    return 0


def _plateau(radii, prof, lo_frac=0.15, hi_frac=0.7):
    """Mean of phi(R) over R in [lo_frac, hi_frac] of the cloud radius: the 'wide range of R'."""
    rmax = radii[-1]
    sel = (radii >= lo_frac * rmax) & (radii <= hi_frac * rmax)
    return float(np.mean(prof[sel])) if np.any(sel) else math.nan


def _report(comm, quick, t1, t2, f3, f5, f6, l2, l3, radii2, prof2, prof2b, radii3, prof3, counts3,
            files, timing):
    L = []
    L.append(f"# mpipack against Degond, Ferreira & Motsch (2017){' — quick run' if quick else ''}\n")
    L.append(f"Written by `mpipack paper{' --quick' if quick else ''}` on {comm.size} rank(s) in "
             f"{timing['total']:.0f} s ({', '.join(f'{k} {v:.0f} s' for k, v in timing.items() if k != 'total')}).\n")
    L.append("T counts iterations; for NAP and NAV it counts inner iterations (outer counts in brackets): "
             "that reading reproduces the paper's Table 1, the outer count is ten times smaller.\n")
    L.append("## Table 1: N = 7, 2D, standard Gaussian starts\n")
    m = t1[("DAHA-NS", 0)]["m"]
    L.append(f"{m} starts per cell{'' if quick else ' (seeds 1-20); the spread is the range of the mean over 10 disjoint sets of 20 seeds'}.\n")
    L.append("| method | eps | T paper | T ours [outer] | spread of mean T | within 20% or spread | sigma^2 paper | sigma^2 ours | A paper | A ours | W-3 paper | W-3 ours: mean (median) | orders within a decade | converged |")
    L.append("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    verdicts = []
    order_checks = []
    for name in T1_PARAMS:
        for k in range(3):
            s = t1[(name, k)]
            tp = PAPER_T[name][k]
            lo, hi = s["spread"]
            ok = abs(s["T"] - tp) <= 0.2 * tp or (lo <= tp <= hi)
            verdicts.append(ok)
            # orders of magnitude (10^floor(log10)); W - 3 only where the paper's run stopped at
            # the optimum (|W - 3| < 1e-2), and 0 matches anything below 1e-14
            def order(v):
                return -15 if abs(v) < 1e-14 else math.floor(math.log10(abs(v)))
            a_ok = abs(order(s["A"]) - order(PAPER_A[name][k])) <= 1
            w_paper = PAPER_W[name][k]
            if abs(w_paper) >= 1e-2:
                w_txt = "A " + ("yes" if a_ok else "NO") + "; W: paper not at the optimum"
                order_checks.append(a_ok)
            else:
                w_ok = abs(order(s["W3_opt"]) - order(w_paper)) <= 1
                w_txt = f"A {'yes' if a_ok else 'NO'}, W {'yes' if w_ok else 'NO'}"
                order_checks.append(a_ok and w_ok)
            if s["n_off"]:
                w_txt += f" ({s['n_off']} start(s) away from the optimum; W compared over the others: {s['W3_opt']:.1e})"
            L.append(f"| {name} | {EPS_T1[k][0]:g} | {tp} | {s['T']:.1f} [{s['outer']:.1f}] | {lo:.0f}-{hi:.0f} | "
                     f"{'yes' if ok else 'NO'} | {PAPER_VAR[name][k]:.3g} | {s['var']:.3g} | "
                     f"{_fmt_order(PAPER_A[name][k])} | {s['A']:.1e} | {_fmt_order(PAPER_W[name][k])} | "
                     f"{s['W3']:.1e} ({s['W3_median']:.1e}) | {w_txt} | {s['conv']}/{s['m']} |")
    L.append(f"\nT within 20% of the paper or inside the spread: {sum(verdicts)}/{len(verdicts)} cells. "
             f"Orders of A and W - 3 within one decade (W where the paper stopped at the optimum): "
             f"{sum(order_checks)}/{len(order_checks)} cells. A is Definition 4.1 literally: the overlap "
             "areas of all pairs at the stop, summed over the starts, over m N A_total. Where some "
             "starts stop at another local minimum (|W - 3| > 1e-3; the paper's NAV-NS rows at "
             "1e-4 and 1e-6 show the same), the orders are compared over the starts that reached "
             "the optimum. NAP-S ends 2 decades closer to W = 3 than the paper reports at "
             "eps = 1e-6 and 1e-8 while its A agrees: why the paper's NAP-S W is further off is not known.\n")
    L.append("## Table 2: convergence to a valid packing (2D)\n")
    L.append(f"A cell passes when every start ({len(range(1, 6 if quick else 11))} for N = 7, "
             f"{len(range(1, 3 if quick else 4))} for N = 100) reaches the stopping test (eps = 1e-6) within "
             f"the budget ({'20000 / 4000' if quick else f'{T2_BUDGET[7]} / {T2_BUDGET[100]}'} iterations for N = 7 / 100, "
             "inner iterations for NAP/NAV) AND the result is a packing: max overlap below 1e-3 d and "
             "|W - 3| < 1e-3 for N = 7, max overlap below 1e-2 d for N = 100. "
             "The caption parameters are tried first (Table 1 for N = 7, Fig. 6 for N = 100; AHA: "
             "(0.01, 0.01) for S as in Fig. 2 and (0.3, 3) for NS; NAV-S: the NAV-NS values), then a "
             f"grid alpha in {T2_SEARCH['alpha']} x beta in {T2_SEARCH['beta']}; a parameter set is "
             "dropped at its first failing start.\n")
    L.append("| method | N | paper | ours | how | tried |")
    L.append("|---|---|---|---|---|---|")
    for r in t2:
        how = next((t["label"] for t in r["tried"] if t["ok"]), "-")
        last = r["tried"][-1]
        L.append(f"| {r['method']}-{r['form']} | {r['n']} | {'yes' if r['paper'] else 'no'} | "
                 f"{'yes' if r['ours'] else 'no'} | {how} | {len(r['tried'])} parameter sets; "
                 f"last: test fired {last['fired']}/{last['runs']}, diverged {last['diverged']}, "
                 f"max overlap {last['max_ov']:.1e} |")
    diffs = [r for r in t2 if r["ours"] != r["paper"]]
    if diffs:
        L.append("\nCells that differ from the paper (findings):\n")
        for r in diffs:
            L.append(f"- {r['method']}-{r['form']} N = {r['n']}: paper {'converges' if r['paper'] else 'fails'}, "
                     f"ours {'converges' if r['ours'] else 'fails'}; tried: " +
                     "; ".join(f"{t['label']}: fired {t['fired']}/{t['runs']}, diverged {t['diverged']}, "
                               f"max overlap {t['max_ov']:.1e}, mean T {t['T']:.0f}"
                               for t in r["tried"][:4]) + ("; ..." if len(r["tried"]) > 4 else ""))
    if any(t["fired"] and t["max_ov"] > 0.9 for r in t2 for t in r["tried"] if r["form"] == "S"):
        L.append("\nA smooth-form run whose test fired with max overlap near 1 d stopped with two centres "
                 "(nearly) on top of each other: grad phi = -2 (X_k - X_l) vanishes there, so neither the "
                 "multiplier (which keeps growing) nor the linearised constraint can push them apart, and "
                 "the relative change goes to zero on a configuration that is not a packing. The validity "
                 "check above is what catches it; the stopping test alone does not.\n")
    L.append("\n## Figures 3-6\n")
    L.append(f"![Fig. 3]({files['fig3']})\n\n![Fig. 4]({files['fig4']})\n\n![Fig. 5]({files['fig5']})\n\n![Fig. 6]({files['fig6']})\n")
    best_c = {f: f3[f][0][int(np.argmin(f3[f][1]))] for f in f3}
    at2 = {f: f3[f][1][int(np.argmin(np.abs(np.array(f3[f][0]) - 2.0)))] for f in f3}
    L.append(f"Fig. 3: the fewest iterations (max over starts) at c = {best_c['NS']:g} (NS, {min(f3['NS'][1])} "
             f"iterations; {at2['NS']} at c = 2) and c = {best_c['S']:g} (S, {min(f3['S'][1])}; {at2['S']} at c = 2); "
             "paper: c about 2 for both. Runs stop at 5000 iterations. c = 0 is not accepted as input "
             "(c must be positive); the smallest c plotted shows the oscillation.\n")
    for name, rs in f6.items():
        conv = sum(r["conv"] for r in rs)
        L.append(f"- Fig. 6, {name}: {conv}/{len(rs)} starts converged, mean T {np.mean([r['T'] for r in rs]):.0f}")
    L.append("\n## Sections 4.3 and 4.4: N = 2000\n")
    f1, _ = l2["first"]
    f2, _ = l2["later"]
    pl2, pl2b, pl3 = _plateau(radii2, prof2), _plateau(radii2, prof2b), _plateau(radii3, prof3)
    L.append(f"2D, N = {l2['n']}, DAHA-S (7.8e-3, 2.8e3, 1.6e-2, 2): the test (4.3) with eps = 1e-5 fired after "
             f"**{l2['fired_at']} iterations** (paper: fewer than 13000) in {l2['wall']:.1f} s. "
             f"Packing density phi(R) averaged over R in [0.15, 0.7] of the cloud radius: **{pl2:.3f}** (paper, Fig. 8: about 0.87; "
             f"hexagonal optimum 0.907); within 0.02 of the paper: {'yes' if abs(pl2 - 0.87) <= 0.02 else 'NO'}.\n")
    L.append(f"What (4.3) does and does not guarantee: it is a relative change per iteration, not a distance to the "
             f"optimum. When it fired: max overlap {f1['max_overlap']:.2e} d, W = {f1['W']:.8g}, density {pl2:.4f}. "
             f"{l2['extra']} iterations later: max overlap {f2['max_overlap']:.2e} d, W = {f2['W']:.8g} "
             f"(relative change of W {abs(f2['W'] - f1['W']) / f1['W']:.1e}), density {pl2b:.4f}. "
             "The packing keeps creeping after the test fires: a slow mode moves it by more than eps per iteration "
             "would suggest, so eps bounds the step, not the error.\n")
    hist = np.bincount(counts3, minlength=15)
    top = np.argsort(hist)[::-1][:3]
    L.append(f"3D, N = {l3['n']}, DAHA-S (2.8e-2, 2.2e2, 5.6e-2, 2), {l3['iters']} iterations in {l3['wall']:.1f} s: "
             f"density plateau **{pl3:.3f}**, maximum {np.max(prof3):.3f} (paper, Fig. 10a: about 0.65); "
             f"within 0.02: {'yes' if abs(max(pl3, np.max(prof3[radii3 > 2])) - 0.65) <= 0.02 else 'NO'}. Neighbours within 1.1 d: "
             f"most common {', '.join(str(int(t)) for t in top)}; share with 8-10: {np.mean((counts3 >= 8) & (counts3 <= 10)):.2f} "
             f"(paper, Fig. 10b: mostly 8-10). Max overlap {l3['final']['max_overlap']:.2e} d.\n")
    L.append(f"![Figs. 8 and 10]({files['fig8_10']})\n")
    return "\n".join(L) + "\n"
