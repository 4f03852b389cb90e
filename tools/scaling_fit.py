"""How do iterations and wall time to a certified packing grow with N? Reads the JSON lines of
`tools/convergence_sweep.py --json FILE` (any number of files, any dimensions), takes per (dim,
N) the median (runs that did not certify counting as the slowest), fits log(median) = a + k
log N by least squares over a range of N, prints the exponent k beside the target 1/b (the
cluster's diameter in sphere diameters grows like N^(1/b)), and draws iterations and seconds
against N (log-log, one colour per dimension, every run as a dot, medians joined; dotted: the
slope N^(1/b) for iterations and N^(1 + 1/b) for seconds, an iteration costing ~N).

    python tools/scaling_fit.py SWEEP.jsonl [...] [--n-min 2000] [--n-max 100000] [--png out.png]

It ends with the convergence targets, each marked met or NOT MET from the runs in the files:
every run certified; iterations growing no faster than N^(1/b) over N = 2000 - 1e5; and in 2D
at N = 2000 every seed certified within a third of the paper's 13000 iterations with W/N^2 at
most 0.0722.

Runs that did not certify count in the "certified" column and, in the medians, as slower than
every certified run (a censored sample): a median that falls on one is not given.
"""

import argparse
import json
import math
import statistics
import sys
from collections import defaultdict


def read(paths):
    """Rows of the sweep files (dicts with n, dim, converged, iterations, seconds)."""
    rows = []
    for path in paths:
        with open(path) as f:
            rows += [json.loads(line) for line in f if line.strip()]
    return rows


def censored_median(values):
    """The median of a sample in which None stands for a run that did not certify (its
    iterations or seconds unknown, but above every certified one's): None when the median falls
    on such a run (half or more did not certify)."""
    xs = sorted(math.inf if v is None else v for v in values)
    if not xs:
        return None
    med = statistics.median(xs)
    return None if math.isinf(med) or math.isnan(med) else med


def medians(rows):
    """{dim: [(n, certified, runs, median iterations, median seconds)]}, N ascending. A run that
    did not certify counts as slower than every certified one (a censored sample), so that a
    failing seed moves the median up instead of dropping out; the medians are None when half
    or more of the runs of that N did not certify."""
    groups = defaultdict(list)
    for r in rows:
        groups[(int(r["dim"]), int(r["n"]))].append(r)
    out = defaultdict(list)
    for (dim, n), rs in sorted(groups.items()):
        ok = [bool(r.get("converged")) for r in rs]
        its = censored_median(r["iterations"] if c else None for r, c in zip(rs, ok))
        secs = censored_median(r["seconds"] if c else None for r, c in zip(rs, ok))
        out[dim].append((n, sum(ok), len(rs), its, secs))
    return dict(out)


def fit_exponent(points):
    """Least-squares slope k and intercept a of log y = a + k log n over (n, y) points (at least
    two distinct n); None when there are too few."""
    pts = [(math.log(n), math.log(y)) for n, y in points if y and y > 0]
    if len({p[0] for p in pts}) < 2:
        return None
    mx = sum(p[0] for p in pts) / len(pts)
    my = sum(p[1] for p in pts) / len(pts)
    sxx = sum((p[0] - mx) ** 2 for p in pts)
    k = sum((p[0] - mx) * (p[1] - my) for p in pts) / sxx
    return k, my - k * mx


def report(table, n_min, n_max):
    """The printed table and fits; returns {dim: (k_iterations, k_seconds)} (None if unfitted)."""
    fits = {}
    for dim, entries in sorted(table.items()):
        print(f"dim {dim}: target exponents: iterations 1/b = {1.0 / dim:.3f}, seconds 1 + 1/b = {1 + 1.0 / dim:.3f}")
        print("       N  certified  median its  median s")
        for n, ok, runs, its, secs in entries:
            its_s = f"{its:10.0f}" if its is not None else "         -"
            secs_s = f"{secs:9.2f}" if secs is not None else "        -"
            print(f"{n:8d}  {ok:4d}/{runs:<4d} {its_s} {secs_s}")
        inside = [e for e in entries if n_min <= e[0] <= n_max and e[3] is not None]
        k_its = fit_exponent([(e[0], e[3]) for e in inside])
        k_sec = fit_exponent([(e[0], e[4]) for e in inside])
        fits[dim] = (k_its[0] if k_its else None, k_sec[0] if k_sec else None)
        span = f"N in [{n_min}, {n_max}]"
        if k_its:
            print(f"  fit over {span} ({len(inside)} sizes): iterations ~ N^{k_its[0]:.2f}, "
                  f"seconds ~ N^{k_sec[0]:.2f}")
        else:
            print(f"  fit over {span}: fewer than two sizes with certified runs")
    return fits


PAPER_ITERATIONS_2D_2000 = 13000  # the paper's iterations at its N = 2000 scene (Table 1)
W_OVER_N2_2D_2000 = 0.0722  # the bound on W/N^2 at 2D N = 2000 (LAMMPS FIRE: 0.0710 - 0.0724)
TARGET_FIT = (2000, 100000)  # the range of N over which the iteration exponent is judged


def targets(rows, table):
    """The convergence targets, judged from the runs: a list of (met, text), printed by main.

    - every run certified, per dimension;
    - the median iterations grow no faster than N^(1/b) over TARGET_FIT (needs two sizes);
    - 2D N = 2000: every seed certified within PAPER_ITERATIONS_2D_2000 / 3 iterations with
      W/N^2 <= W_OVER_N2_2D_2000 (only when such runs are in the files)."""
    out = []
    for dim, entries in sorted(table.items()):
        ok = sum(e[1] for e in entries)
        runs = sum(e[2] for e in entries)
        bad = [f"N={e[0]}: {e[2] - e[1]}" for e in entries if e[1] < e[2]]
        out.append((ok == runs, f"{dim}D: {ok}/{runs} runs certified over N = "
                    f"{entries[0][0]} - {entries[-1][0]}" + (f" (not: {', '.join(bad)})" if bad else "")))
        lo, hi = TARGET_FIT
        inside = [(e[0], e[3]) for e in entries if lo <= e[0] <= hi and e[3] is not None]
        k = fit_exponent(inside)
        if k is not None:
            out.append((k[0] <= 1.0 / dim, f"{dim}D: iterations ~ N^{k[0]:.2f} over N = {lo} - {hi} "
                        f"({len(inside)} sizes), target at most N^{1.0 / dim:.2f}"))
    at2000 = [r for r in rows if int(r["dim"]) == 2 and int(r["n"]) == 2000]
    if at2000:
        limit = PAPER_ITERATIONS_2D_2000 / 3
        good = [r for r in at2000 if r.get("converged") and r["iterations"] <= limit
                and r.get("W_over_N2", math.inf) <= W_OVER_N2_2D_2000]
        worst_its = max(r["iterations"] for r in at2000)
        worst_w = max(r.get("W_over_N2", math.inf) for r in at2000)
        out.append((len(good) == len(at2000),
                    f"2D N = 2000: {len(good)}/{len(at2000)} seeds certified within {limit:.0f} "
                    f"iterations with W/N^2 <= {W_OVER_N2_2D_2000} (at most {worst_its} "
                    f"iterations, W/N^2 up to {worst_w:.5f})"))
    return out


def plot(rows, table, path, n_min=0):
    """The figure; the dotted target slopes start at the first median with N >= n_min (below it
    the runs' time is start-up, not iterations)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    colours = {1: "tab:green", 2: "tab:blue", 3: "tab:red"}
    for ax, key, col, label, extra in ((axes[0], "iterations", 3, "iterations to a certified packing", 0.0),
                                       (axes[1], "seconds", 4, "loop seconds", 1.0)):
        for dim, entries in sorted(table.items()):
            c = colours.get(dim, "k")
            ok = [r for r in rows if int(r["dim"]) == dim and r.get("converged")]
            ax.scatter([r["n"] for r in ok], [r[key] for r in ok], s=10, color=c, alpha=0.35)
            failed = [r for r in rows if int(r["dim"]) == dim and not r.get("converged")
                      and r.get(key) is not None]
            if failed:  # where they stopped: a lower bound
                ax.scatter([r["n"] for r in failed], [r[key] for r in failed], s=30, color=c,
                           marker="x", label=f"{dim}D not certified (at its bound)")
            med = [(e[0], e[col]) for e in entries if e[col] is not None]
            if med:
                ax.plot([m[0] for m in med], [m[1] for m in med], "-o", color=c, label=f"{dim}D median")
                anchored = [m for m in med if m[0] >= n_min] or med
                n0, y0 = anchored[0]
                n1 = med[-1][0]
                slope = extra + 1.0 / dim
                ax.plot([n0, n1], [y0, y0 * (n1 / n0) ** slope], ":", color=c,
                        label=f"N^({slope:.2f}) from N = {n0}")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("N")
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    print(f"plot: {path}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("files", nargs="+")
    ap.add_argument("--n-min", type=int, default=2000)
    ap.add_argument("--n-max", type=int, default=100000)
    ap.add_argument("--png")
    args = ap.parse_args(argv)
    rows = read(args.files)
    if not rows:
        print("scaling_fit: no runs in the files", file=sys.stderr)
        return 2
    table = medians(rows)
    report(table, args.n_min, args.n_max)
    print("targets:")
    for met, text in targets(rows, table):
        print(f"  {'met    ' if met else 'NOT MET'}  {text}")
    if args.png:
        plot(rows, table, args.png, args.n_min)
    return 0


if __name__ == "__main__":
    sys.exit(main())
