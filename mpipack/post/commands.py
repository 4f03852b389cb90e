"""``mpipack post MEASURE RUN``: a measure of a packing read from a run's files, written as a PNG,
its numbers as JSON and its table as CSV next to it, and a short summary on rank 0.

    mpipack post density RUN [--iteration K] [--out DIR]      phi(R) and its plateau
    mpipack post neighbours RUN [--factor 1.1] [--exclude-rattlers]   neighbour-count histogram
    mpipack post contacts RUN [--gap 1e-3]                    Z, rattlers, isostaticity
    mpipack post pressure RUN                                 mu_i: histogram, picture, force chains
    mpipack post gr RUN [--r-max R] [--bins K]                g(r) of the interior
    mpipack post order RUN [--factor 1.1]                     |psi6| (2D), Q6 and Qbar6 (3D)
    mpipack post all RUN                                      every measure above
    mpipack post convergence RUN                              metrics.csv (or the snapshots' figures)
    mpipack post compare RUN RUN ... [--out DIR]              one table and overlaid figures

RUN is a run folder, a snapshots.h5 or a checkpoint.h5. Files go to RUN/post/ (``--out`` to
choose), named after the measure (``-itK`` added for ``--iteration K``). Every number is the
same on any number of ranks. Exit codes: 0, or 2 (bad input: one line on stderr).
"""

import csv
import json
import math
import os
import sys

import numpy as np

from mpipack.errors import EXIT_INPUT, EXIT_OK

from . import figures, source
from .analysis import Analysis

MEASURES = ("density", "neighbours", "contacts", "pressure", "gr", "order")
COMMANDS = MEASURES + ("all", "convergence", "compare")


def add_arguments(parser):
    """The options of ``mpipack post`` (the CLI adds its sub-command parser)."""
    parser.add_argument("measure", metavar="MEASURE",
                        help=f"one of {', '.join(COMMANDS)}, or several measures joined by commas "
                             "(density,neighbours,gr)")
    parser.add_argument("runs", nargs="+", metavar="RUN", help="a run folder, a snapshots.h5 or a checkpoint.h5 "
                        "(compare: several)")
    parser.add_argument("--iteration", type=int, default=None, help="the snapshot of this iteration (default: the last)")
    parser.add_argument("--out", default=None, help="output folder (default RUN/post, compare: the runs' parent/compare)")
    parser.add_argument("--factor", type=float, default=1.1,
                        help="neighbours and order: |X_i - X_j| < factor * d_ij (default 1.1, the paper's Fig. 10b)")
    parser.add_argument("--gap", type=float, default=1e-3, help="contacts: gap below gap * d_ij (default 1e-3)")
    parser.add_argument("--r-max", type=float, default=None, help="g(r) up to this distance (default 5 d, at most half the bulk radius)")
    parser.add_argument("--bins", type=int, default=200, help="g(r) bins (default 200)")
    parser.add_argument("--exclude-rattlers", action="store_true",
                        help="neighbours and order: leave out the rattlers (spheres with fewer than b + 1 "
                             "contacts, found as in contacts) and their pairs")
    parser.add_argument("--quiet", action="store_true", help="no summary lines")


class UsageError(ValueError):
    pass


def measures_asked(text):
    """The measures of a MEASURE argument: "all", one name, or names joined by commas."""
    if text == "all":
        return MEASURES
    names = tuple(t.strip() for t in text.split(","))
    bad = [t for t in names if t not in MEASURES]
    if bad or not names:
        raise UsageError(f"unknown measure {', '.join(bad) or repr(text)}: choose from {', '.join(COMMANDS)}")
    return names


def _check_options(args):
    if not (math.isfinite(args.factor) and args.factor > 0):
        raise UsageError(f"--factor must be a positive number, got {args.factor}")
    if not (math.isfinite(args.gap) and args.gap >= 0):
        raise UsageError(f"--gap must be >= 0, got {args.gap}")
    if args.r_max is not None and not (math.isfinite(args.r_max) and args.r_max > 0):
        raise UsageError(f"--r-max must be a positive number, got {args.r_max}")
    if args.bins < 1:
        raise UsageError(f"--bins must be >= 1, got {args.bins}")
    if args.measure != "compare" and len(args.runs) > 1:
        raise UsageError(f"post {args.measure} takes one RUN ({len(args.runs)} given; compare takes several)")


def main(comm, args):
    say = (lambda *a: print(*a, flush=True)) if comm.rank == 0 and not args.quiet else (lambda *a: None)
    try:
        _check_options(args)
        if args.measure == "compare":
            compare(comm, args, say)
        elif args.measure == "convergence":
            convergence(comm, args, say)
        else:
            measure_run(comm, args.runs[0], measures_asked(args.measure), args, say)
    except (source.PostError, UsageError, OSError) as e:
        if comm.rank == 0:
            print(f"mpipack: error: {_one_line(e)}", file=sys.stderr, flush=True)
        return EXIT_INPUT
    return EXIT_OK


def _one_line(e):
    return " ".join(str(e).split()) or repr(e)


def out_folder(args, file):
    if args.out is not None:
        return os.path.abspath(args.out)
    folder = os.path.dirname(file)
    return os.path.join(folder, "post")


def _prepare_out(comm, out):
    err = None
    if comm.rank == 0:
        try:
            os.makedirs(out, exist_ok=True)
        except OSError as e:
            err = f"--out {out}: {e.strerror or e}"
    err = comm.bcast_object(err)
    if err:
        raise UsageError(err)


def analyse(comm, path, names, args):
    """(packing, its Analysis, {name: Measure}, extras: the rattlers' gids, the force chains)
    of the measures ``names`` of the packing at ``path``."""
    pk = source.read(comm, path, args.iteration)
    d_max = float(comm.allreduce(np.array([pk.diam.max() if len(pk.diam) else 0.0]), "max")[0])
    width = max(args.factor, 1.0 + args.gap) * d_max  # the halo: every neighbour of an owned sphere
    if "gr" in names:  # g(r)'s default r_max is 5 mean diameters, at most 5 d_max
        width = max(width, args.r_max if args.r_max is not None else 5.0 * d_max)
    a = Analysis(comm, pk, width)
    got, extra = {}, {}
    for name in names:
        if name == "contacts":
            got[name], extra["rattlers"] = a.contacts(args.gap)
        elif name == "neighbours":
            got[name] = a.neighbours(args.factor, args.exclude_rattlers, args.gap)
        elif name == "order":
            got[name] = a.order(args.factor, args.exclude_rattlers, args.gap)
        elif name == "gr":
            got[name] = a.gr(args.r_max, args.bins)
        elif name == "pressure":
            got[name] = a.pressure()
            if got[name] is not None and a.dim >= 2:
                extra["chains"] = a.force_chains()
        else:
            got[name] = getattr(a, name)()
    return pk, a, got, extra


def measure_run(comm, path, names, args, say):
    pk, a, got, extra = analyse(comm, path, names, args)
    out = out_folder(args, pk.path)
    _prepare_out(comm, out)
    suffix = "" if args.iteration is None else f"-it{pk.iteration}"
    for name in names:
        m = got[name]
        if m is None:
            say(f"mpipack post {name}: not available for this file "
                f"({'no pressure field' if name == 'pressure' else '1D packing'})")
            continue
        if name == "contacts":
            rattlers = _gather_sorted(comm, extra["rattlers"])
            m.summary["rattler_gids"] = rattlers.tolist() if rattlers is not None and len(rattlers) <= 10000 else \
                (None if rattlers is None else f"{len(rattlers)} (see contacts{suffix}-rattlers.csv)")
        files = write_measure(comm, out, name + suffix, m, pk, a, extra)
        if name == "contacts" and comm.rank == 0:
            with open(os.path.join(out, f"contacts{suffix}-rattlers.csv"), "w") as fh:
                fh.write("gid\n" + "".join(f"{g}\n" for g in rattlers))
        say(f"mpipack post {name}: {headline(name, m.summary, a.d_mean)} -> {files[0]}")
        for w in m.warnings:
            say(f"  warning: {w}")
    return got


def _gather_sorted(comm, values):
    parts = comm.allgather_object(np.asarray(values)) if comm.size > 1 else [np.asarray(values)]
    return np.sort(np.concatenate(parts)) if comm.rank == 0 else None


def headline(name, s, d):
    if name == "density":
        rng = (f" over R = {s['plateau_from'] / d:.1f}..{s['plateau_to'] / d:.1f} d"
               if math.isfinite(s["plateau_from"]) else "")
        inside = (f"; in the {s['container']['kind']} phi = {s['container']['packing_fraction']:.4f}"
                  if "container" in s else "")
        if "container" in s and "bed" in s["container"]:
            inside += f", in the bed {s['container']['bed']['packing_fraction']:.4f}"
        return f"plateau {s['plateau']:.4f}{rng}, phi(R_g) {s['density_at_gyration_radius']:.4f}{inside}"
    if name == "neighbours":
        extra = f", {100 * s['share_8_to_10']:.1f}% with 8-10" if "share_8_to_10" in s else ""
        return f"mean {s['mean']:.3f} neighbours (t = {s['factor']}){extra}"
    if name == "contacts":
        g = s["by_gap"]
        lam = s.get("by_multiplier", {})
        net = lam if "isostaticity" in lam else g
        which = "lambda > 0" if net is lam else f"gap < {s['gap']:g} d"
        zm = f"Z(lambda > 0) {lam['Z']:.3f}, " if lam else ""
        w = s.get("walls")
        walls = ("" if w is None else f"; {w['by_wall_force']} spheres on the walls (wall force > 0), mean "
                 f"wall force {w['mean_wall_force']:.4g}" if "by_wall_force" in w else
                 f"; {w['by_gap']} spheres on the walls (gap < {s['gap']:g} r)")
        return (f"{zm}Z(gap < {s['gap']:g} d) {g['Z']:.3f}; {net['rattlers']} rattlers ({which}), "
                f"Z - 2b = {net['isostaticity']:+.3f} without them{walls}")
    if name == "pressure":
        return f"mean mu {s['mean']:.4g}, std {s['std']:.4g}, max/mean {s['max_over_mean']:.3g}"
    if name == "gr":
        return (f"first peak g = {s['first_peak_g']:.3g} at r = {s['first_peak_r_over_d']:.3f} d "
                f"({s['centres']} interior centres)")
    if name == "order":
        if "mean_abs_psi6" in s:
            return f"mean |psi6| {s['mean_abs_psi6']:.4f}, |mean psi6| {s['abs_mean_psi6']:.4f}"
        return (f"mean Q6 {s['mean_Q6']:.4f}, mean Qbar6 {s['mean_Q6_averaged']:.4f}, "
                f"crystalline {100 * s['crystalline_share']:.1f}%")
    return ""


def _jsonable(v):
    if isinstance(v, dict):
        return {k: _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    if isinstance(v, np.ndarray):
        return [_jsonable(x) for x in v.tolist()]
    if isinstance(v, (np.integer,)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        return float(v) if math.isfinite(v) else None
    return v


def write_measure(comm, out, stem, m, pk, a, extra):
    """PNG, JSON and CSV of one measure (rank 0 writes). Returns the paths."""
    paths = [os.path.join(out, stem + ext) for ext in (".png", ".json", ".csv")]
    if comm.rank != 0:
        return paths
    doc = {"measure": m.name, "file": pk.path, "kind": pk.kind, "iteration": pk.iteration, "n": pk.n,
           "dim": pk.dim, "mean_diameter": a.d_mean, "summary": m.summary, "warnings": m.warnings}
    with open(paths[1], "w") as fh:
        json.dump(_jsonable(doc), fh, indent=1)
        fh.write("\n")
    write_csv(paths[2], m.table)
    draw(paths[0], m, pk, a, extra)
    for suffix, (table, picture) in m.parts.items():  # a container's profiles
        write_csv(os.path.join(out, f"{stem}-{suffix}.csv"), table)
        figures.profile(os.path.join(out, f"{stem}-{suffix}.png"), picture, m.warnings)
    return paths


def write_csv(path, table):
    names = list(table)
    cols = [np.asarray(table[k]) for k in names]
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(names)
        for row in zip(*cols):
            w.writerow([repr(float(v)) if isinstance(v, (float, np.floating)) else int(v) for v in row])


def draw(path, m, pk, a, extra):
    if m.name == "density":
        figures.density(path, m)
    elif m.name == "neighbours":
        figures.histogram(path, m, "neighbours", "share", f"neighbours (|X_i - X_j| < {m.summary['factor']} d_ij)")
    elif m.name == "contacts":
        figures.histogram(path, m, "contacts", "spheres_by_gap", f"contacts (gap < {m.summary['gap']:g} d)",
                          ylabel="spheres")
    elif m.name == "gr":
        figures.curve(path, m.picture["r"], m.picture["g"], "r / d", "g(r)", m.warnings, hline=1.0)
    elif m.name == "pressure":
        figures.histogram(path, m, "mu_from", "spheres", "pressure mu_i = sum_j lambda_ij", ylabel="spheres")
        if m.picture is not None and pk.dim >= 2:
            stem = os.path.splitext(path)[0]
            figures.spheres(stem + "-map.png", m.picture, m.picture["pressure"], "pressure mu_i", m.warnings,
                            dim=pk.dim)
            chains = extra.get("chains")
            if chains is not None:
                figures.spheres(stem + "-chains.png", chains, None, "", m.warnings, chains=chains, dim=pk.dim)
    elif m.name == "order":
        if pk.dim == 2:
            figures.histogram(path, m, "abs_psi6_from", "spheres", "|psi6|", ylabel="spheres")
            if m.picture is not None:
                stem = os.path.splitext(path)[0]
                figures.spheres(stem + "-map.png", m.picture, m.picture["abs_psi6"], "|psi6|", m.warnings)
                figures.spheres(stem + "-grains.png", m.picture, m.picture["angle"], "grain orientation (rad)",
                                m.warnings, cmap="hsv")
        else:
            figures.histogram(path, m, "Q6_from", "spheres_Q6", "Q6", ylabel="spheres")
            if m.picture is not None:
                figures.spheres(os.path.splitext(path)[0] + "-map.png", m.picture, m.picture["Q6"], "Q6",
                                m.warnings, dim=3)


# ---- convergence -------------------------------------------------------------------------------

def convergence(comm, args, say):
    """Relative change, max overlap, W and KKT residual against iteration and wall time, from
    metrics.csv (or, without it, from the snapshots' attributes)."""
    path = os.path.abspath(args.runs[0])
    folder = path if os.path.isdir(path) else os.path.dirname(path)
    err, columns, origin = None, None, None
    if comm.rank == 0:
        try:
            columns, origin = _convergence_columns(folder)
        except (source.PostError, OSError, ValueError) as e:
            err = _one_line(e)
    err = comm.bcast_object(err)
    if err:
        raise source.PostError(err)
    out = args.out and os.path.abspath(args.out) or os.path.join(folder, "post")
    _prepare_out(comm, out)
    if comm.rank != 0:
        return
    warnings = []
    if len(columns["iteration"]) < 2:
        warnings.append(f"only {len(columns['iteration'])} row(s) in {origin}")
    png = figures.convergence(os.path.join(out, "convergence.png"), columns, warnings)
    write_csv(os.path.join(out, "convergence.csv"), columns)
    last = {k: float(v[-1]) for k, v in columns.items() if len(v)}
    with open(os.path.join(out, "convergence.json"), "w") as fh:
        json.dump(_jsonable({"measure": "convergence", "source": origin, "rows": len(columns["iteration"]),
                             "last": last, "warnings": warnings}), fh, indent=1)
    say(f"mpipack post convergence: {len(columns['iteration'])} rows from {os.path.basename(origin)}, last "
        f"max overlap {last.get('max_overlap', math.nan):.3g}, KKT {last.get('kkt_residual', math.nan):.3g} -> {png}")
    for w in warnings:
        say(f"  warning: {w}")


def _convergence_columns(folder):
    metrics = os.path.join(folder, "metrics.csv")
    keys = ("iteration", "wall_seconds", "relative_change", "max_overlap", "W", "kkt_residual")
    if os.path.isfile(metrics):
        with open(metrics, newline="") as fh:
            rows = list(csv.DictReader(fh))
        if rows and all(k in rows[0] for k in keys):
            return {k: np.array([float(r[k]) for r in rows]) for k in keys}, metrics
        raise source.PostError(f"{metrics}: not an mpipack metrics file (columns {list(rows[0]) if rows else []})")
    snaps = os.path.join(folder, "snapshots.h5")
    if not os.path.isfile(snaps):
        raise source.PostError(f"{folder}: no metrics.csv (run with --set output.metrics_every=K) and no snapshots.h5")
    from mpipack.io import _h5
    with _h5.h5py().File(snaps, "r") as f:
        groups = [f["snapshots"][k] for k in sorted(f.get("snapshots", {}))]
        table = {k: np.array([float(g.attrs.get(k, math.nan)) for g in groups]) for k in keys}
    return table, snaps


# ---- compare -----------------------------------------------------------------------------------

COMPARED = (("density", "plateau"), ("density", "density_at_gyration_radius"), ("neighbours", "mean"),
            ("contacts", "Z"), ("contacts", "Z_without_rattlers"), ("contacts", "rattler_share"),
            ("order", "mean_abs_psi6"), ("order", "mean_Q6"), ("order", "crystalline_share"),
            ("pressure", "max_over_mean"))


# what each run's summary.json says of it, beside the measures (empty without a summary)
RUN_COLUMNS = ("seed", "exit_code", "converged", "iterations", "wall_seconds", "max_overlap", "kkt_residual")


def _cell(v):
    return "" if v is None else repr(v) if isinstance(v, float) else str(v)


def _value(got, name, key):
    m = got.get(name)
    if m is None:
        return None
    s = m.summary.get("by_gap", m.summary) if name == "contacts" else m.summary
    v = s.get(key)
    return float(v) if isinstance(v, (int, float)) else None


def compare(comm, args, say):
    """The same measures of several runs: one table (CSV, JSON, markdown on stdout) with mean
    and spread, and overlaid phi(R) and neighbour histograms."""
    runs = [os.path.abspath(r) for r in args.runs]
    names = ("density", "neighbours", "contacts", "order", "pressure")
    rows, curves_phi, curves_nb, warnings = [], [], [], []
    for run in runs:
        pk, a, got, _ = analyse(comm, run, names, args)
        row = {"run": run, "label": os.path.basename(run.rstrip("/")) or run, "iteration": pk.iteration,
               "n": pk.n, "dim": pk.dim, **{k: pk.summary.get(k) for k in RUN_COLUMNS}}
        for name, key in COMPARED:
            v = _value(got, name, key)
            if v is not None:
                row[f"{name}.{key}"] = v
        rows.append(row)
        label = row["label"]
        curves_phi.append((label, got["density"].picture["R"] / a.d_mean, got["density"].picture["phi"]))
        curves_nb.append((label, got["neighbours"].picture["k"], got["neighbours"].picture["hist"] / pk.n))
        warnings += [f"{label}: {w}" for w in sorted({w for m in got.values() if m is not None for w in m.warnings})]
    dims = {r["dim"] for r in rows}
    if len(dims) > 1:
        raise UsageError(f"compare: the runs have different dimensions {sorted(dims)}")
    keys = [f"{n}.{k}" for n, k in COMPARED if all(f"{n}.{k}" in r for r in rows)]
    stats = {}
    for k in keys:
        v = np.array([r[k] for r in rows])
        stats[k] = {"mean": float(v.mean()), "std": float(v.std(ddof=1)) if len(v) > 1 else 0.0,
                    "min": float(v.min()), "max": float(v.max())}
    out = os.path.abspath(args.out) if args.out else os.path.join(os.path.dirname(os.path.commonpath(runs)) if
                                                                   len(runs) == 1 else os.path.commonpath(runs), "compare")
    _prepare_out(comm, out)
    if comm.rank != 0:
        return
    certified = sum(r.get("exit_code") == 0 and r.get("converged") is True for r in rows)
    with open(os.path.join(out, "compare.json"), "w") as fh:
        json.dump(_jsonable({"runs": rows, "certified": certified, "statistics": stats, "warnings": warnings}),
                  fh, indent=1)
    with open(os.path.join(out, "compare.csv"), "w", newline="") as fh:
        w = csv.writer(fh)
        head = ["label", "iteration", "n"] + list(RUN_COLUMNS)
        w.writerow(head + keys)
        for r in rows:
            w.writerow([_cell(r[k]) for k in head] + [repr(r[k]) for k in keys])
        for stat in ("mean", "std"):
            w.writerow([stat] + [""] * (len(head) - 1) + [repr(stats[k][stat]) for k in keys])
    figures.overlay(os.path.join(out, "compare-density.png"), curves_phi, "R / d", "phi(R)", warnings)
    figures.overlay(os.path.join(out, "compare-neighbours.png"), curves_nb, "neighbours", "share of spheres", warnings)
    say(f"mpipack post compare: {len(rows)} runs, {certified} certified -> {out}")
    say("| measure | " + " | ".join(["mean", "std", "min", "max"]) + " |")
    say("|---|---|---|---|---|")
    for k in keys:
        s = stats[k]
        say(f"| {k} | {s['mean']:.5g} | {s['std']:.3g} | {s['min']:.5g} | {s['max']:.5g} |")
    for w in warnings:
        say(f"  warning: {w}")
