"""The work-precision frontier, side by side (issue 42): for one start, the wall time at which
each code and protocol first reaches each quality level, every recorded state scored by the
same function (score.score_state).

    bash tools/peers/setup_lammps.sh && . tools/peers/lammps_env.sh
    MPIPACK_CMD="/work/main/.venv/bin/python -m mpipack.cli" \\
    $LAMMPS_PYTHON tools/peers/frontier.py --dim 3 --n 2000 --ranks 1 --time-limit 120 \\
        --png docs/fig-frontier-3d-n2000.png
    $LAMMPS_PYTHON tools/peers/frontier.py --report mpipack-out/frontier/frontier-d3-n2000-r1-s1.json  # table + figure again

Codes (--codes):

- ``quench``: LAMMPS FIRE, the two-stage K continuation of compare.py (lammps_fire.py defaults);
- ``stiff``: LAMMPS FIRE in one stage at the quench's final K (k_estimate for a 6e-4 d
  overlap), one ``minimize`` to ||F|| <= 1e-3 ||grad W||;
- ``damped``: LAMMPS damped MD (``fix nve/limit`` + ``fix viscous``), same K and stop;
- ``mpipack``: ``mpipack run`` with its default certified stop;
- ``jammed``: ``mpipack run --set stop.rule=jammed``.

Records. LAMMPS: positions every --trace-every steps by a ``fix external`` callback
(lammps_fire.Recorder: FIRE is not restarted; the callback's own seconds are measured and
taken off the clock). mpipack: ``output.snapshot_every`` snapshots (the start, every K
iterations, the end) with their ``wall_seconds``; the snapshot writes are taken off: snapshot
k (k = 0 the start) is preceded by k writes, each costing on average the run's
``snapshot_seconds`` / snapshots (summary.json). Start-up is off the clock for both (LAMMPS:
the first neighbour build, ``run 0``; mpipack: ``setup_seconds``).

Scores: max overlap and W from positions (score.score); the KKT residual: LAMMPS, the net
force ||F|| / ||grad W|| with the penalty forces as multipliers computed from the positions
and K (score.penalty_kkt_residual); mpipack, the residual its snapshot reports (the run's own
multipliers, the same definition ||grad W + sum lambda grad phi|| / ||grad W||), and for the
end state the certificate's (which may use fitted multipliers). Levels (score.levels_reached):
max overlap <= 1e-3 d and (W - W_best)/W_best <= 1e-1 ... 3e-4, W_best the lowest W any code
reached with max overlap <= 1e-3 d; max overlap <= 1e-3 d and KKT <= 1e-1, 3e-2, 1e-2.
"""

import argparse
import json
import math
import os
import shlex
import subprocess
import sys
import tempfile
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(os.path.dirname(HERE))
sys.path.insert(0, HERE)
import mpipack_side  # noqa: E402
import score  # noqa: E402

LAMMPS_VENV = os.path.join(HERE, ".venv-lammps")
LAMMPS_CODES = ("quench", "stiff", "damped")
MPIPACK_CODES = {"mpipack": mpipack_side.CERTIFIED_SETS, "jammed": ["stop.rule=jammed", "stop.max_iter=100000000"]}
LABELS = {"quench": "LAMMPS FIRE two-stage quench", "stiff": "LAMMPS FIRE stiff single stage",
          "damped": "LAMMPS damped MD (nve/limit + viscous)", "mpipack": "mpipack certified (default)",
          "jammed": "mpipack stop.rule=jammed"}


def level_keys():
    return [f"W<={lv:g}" for lv in score.W_LEVELS] + [f"KKT<={lv:g}" for lv in score.KKT_LEVELS]


# ---- LAMMPS ------------------------------------------------------------------------------------

def read_lammps_trace(path, ranks, diam):
    """Records of lammps_fire.Recorder (one file per rank when ranks > 1), merged by atom id
    (id = global row + 1): a list of (step, seconds, K, x (N, b) in start order)."""
    files = [path] if ranks == 1 else [f"{path[:-4]}.rank{r}.npz" for r in range(ranks)]
    parts = [dict(np.load(f)) for f in files]
    n = diam.shape[0]
    first = parts[0]
    out = []
    offs = [np.concatenate([[0], np.cumsum(p["counts"])]) for p in parts]
    for k in range(first["steps"].size):
        x = np.full((n, int(first["dim"])), np.nan)
        for p, o in zip(parts, offs):
            rows = slice(o[k], o[k + 1])
            x[p["tag"][rows] - 1] = p["x"][rows]
        if np.isnan(x).any():
            raise SystemExit(f"frontier: record {k} of {path} misses atoms")
        # rank 0's clock (the ranks step together; their clocks differ by the callback's skew)
        out.append((int(first["steps"][k]), float(first["seconds"][k]), float(first["K"][k]), x))
    return out


def failed(what, code, stderr, argv):
    """A protocol that ended without its result (no JSON, no summary): no states, and why, so
    that the case goes on with the other codes and the table says "failed"."""
    print(f"frontier: {what} failed (exit {code}): {stderr[-1500:]}", file=sys.stderr, flush=True)
    return [], {"failed": f"exit {code}", "stderr_tail": stderr[-1500:], "argv": " ".join(map(str, argv))}


def run_lammps(code, start, ranks, workdir, args):
    py = os.path.join(LAMMPS_VENV, "bin", "python")
    trace = os.path.join(workdir, f"trace-{code}.npz")
    out_json = os.path.join(workdir, f"lammps-{code}.json")
    argv = [py, os.path.join(HERE, "lammps_fire.py"), start, "--protocol", code, "--trace", trace,
            "--trace-every", str(args.trace_every), "--json", out_json, "--log-dir", workdir]
    if args.time_limit:
        argv += ["--time-limit", str(args.time_limit)]
    argv += shlex.split(getattr(args, f"{code}_args") or "")
    if ranks > 1:
        argv = [os.path.join(LAMMPS_VENV, "bin", "mpiexec"), "-n", str(ranks)] + argv
    env = dict(os.environ)
    env["LD_LIBRARY_PATH"] = os.path.join(LAMMPS_VENV, "lib") + (
        os.pathsep + env["LD_LIBRARY_PATH"] if env.get("LD_LIBRARY_PATH") else "")
    p = subprocess.run(argv, env=env, capture_output=True, text=True)
    if not os.path.exists(out_json):
        return failed(f"lammps_fire.py {code}", p.returncode, p.stderr, argv)
    with open(out_json) as f:
        res = json.load(f)
    d = np.load(start)
    diam = np.broadcast_to(np.asarray(d["diam"], dtype=float), (d["x"].shape[0],))
    states = []
    for step, sec, K, x in read_lammps_trace(trace, ranks, diam):
        states.append({"step": step, "seconds": sec, **score.score_state(x, diam, K=K)})
    info = {"protocol": res.get("protocol"), "reached_own_stop": res.get("reached"),
            "stop_reason": res.get("stop_reason"), "seconds": res.get("seconds"), "steps": res.get("steps"),
            "callback_seconds_excluded": res.get("trace_callback_seconds"), "argv": " ".join(argv[1:] if ranks == 1 else argv)}
    return states, info


# ---- mpipack -----------------------------------------------------------------------------------

READ_SNAPSHOTS = r"""
import sys, json, h5py, numpy as np
path, out = sys.argv[1], sys.argv[2]
with h5py.File(path, "r") as f:
    names = sorted(f["snapshots"])
    its = [int(f["snapshots"][k].attrs["iteration"]) for k in names]
    secs = [float(f["snapshots"][k].attrs["wall_seconds"]) for k in names]
    kkt = [float(f["snapshots"][k].attrs["kkt_residual"]) for k in names]
    x = np.stack([f["snapshots"][k]["position"][...] for k in names])
    diam = f["snapshots"][names[0]]["diameter"][...]
np.savez(out, iteration=np.array(its), wall_seconds=np.array(secs), kkt=np.array(kkt), x=x, diam=diam)
"""


def mpipack_python():
    if os.environ.get("MPIPACK_PYTHON"):
        return os.environ["MPIPACK_PYTHON"]
    cmd = mpipack_side.mpipack_command()
    py = cmd[0] if os.path.basename(cmd[0]).startswith("python") else os.path.join(os.path.dirname(cmd[0]), "python")
    if not os.path.exists(py):
        raise SystemExit(f"frontier: no python with h5py and matplotlib at {py}: set MPIPACK_CMD "
                         f"(e.g. \"/path/to/.venv/bin/python -m mpipack.cli\") or MPIPACK_PYTHON")
    return py


def run_mpipack(code, start, ranks, workdir, args):
    with open(start[:-4] + ".json") as f:
        meta = json.load(f)
    out = os.path.join(workdir, f"mpipack-{code}")
    sets = list(MPIPACK_CODES[code]) + [f"output.snapshot_every={args.snapshot_every}"]
    if args.time_limit:
        sets.append(f"stop.max_seconds={args.time_limit}")
    sets += shlex.split(getattr(args, f"{code}_args") or "")
    rc, summary, wall, err = mpipack_side.run_mpipack(meta, ranks, out, None, sets=sets)
    if summary is None:
        return failed(f"mpipack {code}", rc, err, sets)
    npz = os.path.join(workdir, f"snapshots-{code}.npz")
    p = subprocess.run([mpipack_python(), "-c", READ_SNAPSHOTS, os.path.join(out, "snapshots.h5"), npz],
                       env=mpipack_side.mpipack_env(), capture_output=True, text=True)
    if p.returncode != 0:
        raise SystemExit(f"frontier: reading mpipack's snapshots failed: {p.stderr[-1500:]}")
    d = np.load(npz)
    count = d["iteration"].size
    per_write = float(summary.get("snapshot_seconds") or 0.0) / max(1, count)
    states = []
    for k in range(count):
        kkt = float(d["kkt"][k])
        if k == count - 1 and int(d["iteration"][k]) == int(summary["iterations"]):
            kkt = float(summary["kkt_residual"])     # the certificate's residual of the end state
        sec = float(d["wall_seconds"][k]) - k * per_write if k else 0.0
        states.append({"step": int(d["iteration"][k]), "seconds": max(0.0, sec),
                       **score.score_state(d["x"][k], d["diam"], kkt=kkt)})
    info = {"sets": sets, "exit": rc, "iterations": summary.get("iterations"),
            "seconds": summary.get("loop_seconds"), "setup_seconds": summary.get("setup_seconds"),
            "snapshot_seconds_excluded": summary.get("snapshot_seconds"), "snapshots": count,
            "converged": summary.get("converged"), "stop_reason": summary.get("stop_reason"),
            "kkt_residual_final": summary.get("kkt_residual")}
    return states, info


# ---- report ------------------------------------------------------------------------------------

def analyse(result):
    """W_best over all codes, then each code's levels (in place)."""
    traces = [c["states"] for c in result["codes"].values()]
    wb = score.best_w(traces)
    result["W_best"] = wb
    for c in result["codes"].values():
        c["levels"] = score.levels_reached(c["states"], wb)
    return result


def fmt_s(v):
    return "not reached" if v is None else f"{v:.2f}"


def table(result):
    keys = level_keys()
    case = result["case"]
    wb = result["W_best"]
    best = f"W_best/N² = {wb / case['n'] ** 2:.6f}" if wb is not None else "no state within 1e-3 d of overlap"
    lines = [f"{case['dim']}D, N = {case['n']}, {case['ranks']} rank(s), seed {case['seed']}; "
             f"{best}; load average {result['loadavg'][0]:.1f} "
             f"({result['time']})", "",
             "| code | " + " | ".join(k.replace("<=", " ≤ ") for k in keys) + " | final W/N² | final overlap | final KKT |",
             "|---" * (len(keys) + 4) + "|"]
    for name, c in result["codes"].items():
        if not c["states"]:
            lines.append(f"| {LABELS.get(name, name)} | " + " | ".join("failed" for _ in keys)
                         + f" | failed ({c['info'].get('failed', 'no states')}) | | |")
            continue
        last = c["states"][-1]
        lines.append(f"| {LABELS.get(name, name)} | " + " | ".join(fmt_s(c["levels"][k]) for k in keys)
                     + f" | {last['W_over_N2']:.6f} | {last['max_overlap']:.1e} | {last['kkt']:.1e} |")
    cells = [f"×{v:.2f}" if isinstance(v, float) else v for v in versus(result).values()]
    lines.append("| mpipack's best ÷ LAMMPS's best | " + " | ".join(cells) + " | | | |")
    return "\n".join(lines)


def versus(result):
    """Per level (``level_keys``): the first time any mpipack code reached it over the first
    time any LAMMPS protocol did (the issue's target: at most 1/3), or who alone reached it
    ("mpipack alone", "LAMMPS alone", "neither"). Codes merged by ``--report`` are named
    "code@tag"."""
    out = {}
    for k in level_keys():
        best = {True: None, False: None}   # is a LAMMPS protocol -> its best seconds
        for name, c in result["codes"].items():
            t = c["levels"].get(k)
            lammps = name.split("@")[0] in LAMMPS_CODES
            if t is not None and (best[lammps] is None or t < best[lammps]):
                best[lammps] = t
        ours, theirs = best[False], best[True]
        if ours is not None and theirs is not None:
            out[k] = ours / theirs if theirs > 0 else math.inf
        else:
            out[k] = {(True, False): "mpipack alone", (False, True): "LAMMPS alone"}.get(
                (ours is not None, theirs is not None), "neither")
    return out


def plot(result, png):
    try:
        import matplotlib
    except ImportError:  # the LAMMPS venv has no matplotlib: mpipack's python draws it
        tmp = tempfile.NamedTemporaryFile("w", suffix=".json", delete=False)
        json.dump(result, tmp)
        tmp.close()
        subprocess.run([mpipack_python(), os.path.abspath(__file__), "--report", tmp.name, "--png", png,
                        "--no-table"], env=mpipack_side.mpipack_env(), check=True)
        os.remove(tmp.name)
        return
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    keys = level_keys()
    fig, ax = plt.subplots(figsize=(8, 4.5))
    nw = len(score.W_LEVELS)
    case = result["case"]
    where = f"{case['dim']}D N = {case['n']}, {case['ranks']} rank(s)"
    if not any(v is not None for c in result["codes"].values() for v in c["levels"].values()):
        # no code reached any level (2D N = 2e5 within 600 s): how close each came instead
        for name, c in result["codes"].items():
            pts = [(st["seconds"], st["max_overlap"]) for st in c["states"] if st["max_overlap"] > 0]
            ax.plot([p[0] for p in pts], [p[1] for p in pts], marker="o", ms=3, label=LABELS.get(name, name))
        ax.axhline(score.FRONTIER_OVERLAP, color="grey", lw=0.8)
        ax.set_xlabel("wall seconds")
        ax.set_ylabel("max overlap / d (log); every level asks 1e-3")
        title = f"{where}: no code reached a level; max overlap against time (load {result['loadavg'][0]:.0f})"
    else:
        for name, c in result["codes"].items():
            ys = [c["levels"][k] for k in keys]
            color = None
            for group in (range(nw), range(nw, len(keys))):   # W levels, KKT levels: two lines
                xs = [i for i in group if ys[i] is not None]
                if not xs and color is not None:
                    continue
                line, = ax.plot(xs, [ys[i] for i in xs], marker="o", color=color,
                                label=LABELS.get(name, name) if color is None else None)
                color = line.get_color()
        ax.set_xticks(range(len(keys)))
        ax.set_xticklabels([k.replace("<=", "≤") for k in keys], rotation=30)
        ax.set_ylabel("wall seconds to first reach (log)")
        ax.axvline(nw - 0.5, color="grey", lw=0.8)
        ax.set_xlabel("level (a missing point: not reached)")
        title = (f"{where}: time to each level "
                 f"(overlap ≤ 1e-3 d for all; shared machine, load {result['loadavg'][0]:.0f})")
    ax.set_yscale("log")
    ax.set_title(title, fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(png, dpi=110)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--dim", type=int, default=3)
    p.add_argument("--n", type=int, default=2000)
    p.add_argument("--ranks", type=int, default=1)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--codes", nargs="+", default=["quench", "stiff", "damped", "mpipack", "jammed"],
                   choices=list(LAMMPS_CODES) + list(MPIPACK_CODES))
    p.add_argument("--time-limit", type=float, default=120.0, help="seconds of relaxation per code (0: none)")
    p.add_argument("--trace-every", type=int, default=200, help="LAMMPS: steps between records")
    p.add_argument("--snapshot-every", type=int, default=200, help="mpipack: iterations between snapshots")
    for c in list(LAMMPS_CODES) + list(MPIPACK_CODES):
        p.add_argument(f"--{c}-args", default="", help=f"extra options for {c} (lammps_fire.py options / --set k=v)")
    p.add_argument("--out", default=os.path.join(REPO, "mpipack-out", "frontier"))
    p.add_argument("--png", default=None)
    p.add_argument("--report", nargs="+", default=None,
                   help="result .json file(s): only the table and the figure (several: merged, one W_best, "
                        "codes named code@folder, e.g. a parameter sweep)")
    p.add_argument("--no-table", action="store_true")
    args = p.parse_args(argv)
    if args.report:
        result = None
        for path in args.report:
            with open(path) as f:
                r = json.load(f)
            if len(args.report) > 1:  # a sweep: one W_best over all; codes named by their folder
                tagname = os.path.basename(os.path.dirname(os.path.abspath(path)))
                r["codes"] = {f"{k}@{tagname}": v for k, v in r["codes"].items()}
            if result is None:
                result = r
            else:
                result["codes"].update(r["codes"])
        result = analyse(result)
        if not args.no_table:
            print(table(result))
        if args.png:
            plot(result, args.png)
        return 0
    os.makedirs(args.out, exist_ok=True)
    sigma = (args.n / 2000.0) ** (1.0 / args.dim)
    start = os.path.join(args.out, f"start-d{args.dim}-n{args.n}-s{args.seed}.npz")
    if not os.path.exists(start):
        mpipack_side.make_start(args.n, args.dim, sigma, args.seed, start)
    tag = f"d{args.dim}-n{args.n}-r{args.ranks}-s{args.seed}"
    workdir = os.path.join(args.out, f"work-{tag}")
    os.makedirs(workdir, exist_ok=True)
    path = os.path.join(args.out, f"frontier-{tag}.json")
    result = {"case": {"dim": args.dim, "n": args.n, "ranks": args.ranks, "seed": args.seed, "sigma": sigma},
              "time": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "loadavg": os.getloadavg(),
              "time_limit": args.time_limit, "codes": {}}
    if os.path.exists(path):  # add to / redo codes of an earlier session of this case
        with open(path) as f:
            result["codes"] = json.load(f).get("codes", {})
    for code in args.codes:
        load = os.getloadavg()
        if code in LAMMPS_CODES:
            states, info = run_lammps(code, start, args.ranks, workdir, args)
        else:
            states, info = run_mpipack(code, start, args.ranks, workdir, args)
        info["loadavg_before"] = load
        info["loadavg_after"] = os.getloadavg()
        result["codes"][code] = {"info": info, "states": states}
        print(f"{code}: {len(states)} states, {info.get('seconds')} s, load {load[0]:.1f}", flush=True)
        with open(path, "w") as f:
            json.dump(result, f)
    analyse(result)
    with open(path, "w") as f:
        json.dump(result, f)
    print(table(result))
    if args.png:
        plot(result, args.png)
    print(f"result: {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
