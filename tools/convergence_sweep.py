"""Does the main job certify at every N? Runs `mpipack run --set n=N --seed S` (default scene
otherwise, no tuning) for a ladder of N and seeds, and prints one row per run and a summary per
N: certified or not, iterations, seconds, iterations until the explosion of the dense start is
over (max overlap first below 0.1 d), W/N^2, and the certificate's figures.

    python tools/convergence_sweep.py --n 500,2000,8000 --seeds 0-4 [--dim 3] [--ranks 2]
        [--max-iter 40000] [--set key=value ...] [--json out.jsonl]

Each run is a real command-line run in its own temporary folder; exit codes are reported. A
run stops itself before --timeout (``stop.max_seconds``, unless --set gives one) and reports
its figures with exit 4; one that does not is killed and reported as "timeout".
"""

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time


def seeds_of(text):
    out = []
    for part in text.split(","):
        if "-" in part:
            a, b = part.split("-")
            out += list(range(int(a), int(b) + 1))
        else:
            out.append(int(part))
    return out


def loop_seconds(timeout):
    """The run's own time limit (stop.max_seconds) under the sweep's timeout: a tenth of it, at
    least 10 s and at most 120 s, left for start-up, the certificate, the snapshots and the
    summary (stop.max_seconds bounds the loop alone; 2D N = 32000 on a loaded 2-core machine took
    3.7 s to set up and 3.5 s to write its snapshots, past a 5 s margin)."""
    return max(1.0, timeout - min(max(0.1 * timeout, 10.0), 120.0))


def run_one(n, seed, args):
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [sys.executable, "-m", "mpipack.cli", "run", "--seed", str(seed), "--set", f"n={n}",
               "--set", f"dim={args.dim}", "--set", f"stop.max_iter={args.max_iter}",
               "--out", tmp, "--quiet", "--set", "output.snapshots=false"]
        for s in args.set:
            cmd += ["--set", s]
        if not any(x.startswith("stop.max_seconds=") for x in args.set):
            # the run stops itself before the timeout, with its summary and figures (exit 4),
            # instead of being killed with nothing to show
            cmd += ["--set", f"stop.max_seconds={loop_seconds(args.timeout):g}"]
        if args.ranks > 1:
            cmd = ["mpirun", "--oversubscribe", "-n", str(args.ranks)] + cmd
        t0 = time.perf_counter()
        try:
            proc = subprocess.run(cmd, capture_output=True, text=True, timeout=args.timeout)
            returncode, stderr = proc.returncode, proc.stderr
        except subprocess.TimeoutExpired as e:  # the safety net: a run that did not stop itself
            returncode = "timeout"
            stderr = (e.stderr.decode() if isinstance(e.stderr, bytes) else (e.stderr or ""))
            stderr += f"\nkilled after the sweep's timeout of {args.timeout:g} s"
        wall = time.perf_counter() - t0
        path = os.path.join(tmp, "summary.json")
        s = json.load(open(path)) if os.path.exists(path) else {}
    cert = s.get("certificate", {})
    sched = s.get("schedule") or {}
    return {"n": n, "dim": args.dim, "seed": seed, "ranks": args.ranks, "exit": returncode,
            "converged": s.get("converged"), "stop_reason": s.get("stop_reason"),
            "iterations": s.get("iterations"),
            "seconds": round(s.get("wall_seconds", wall), 2),
            "explosion_iterations": sched.get("switch_iteration"),
            # the schedule's state at the end: multiplier steps, FIRE restarts, penalty factor
            "dual_steps": sched.get("dual_steps"), "restarts": sched.get("restarts"),
            "penalty_factor": sched.get("penalty_factor"),
            "W_over_N2": s["W"] / n ** 2 if "W" in s else None,
            "max_overlap": cert.get("overlap", {}).get("value"),
            "kkt": cert.get("kkt", {}).get("value"),
            # "fitted" when the certificate's multipliers are the fit's (mpipack/stop/fit.py), and
            # the run's own multipliers' residual
            "kkt_multipliers": cert.get("kkt", {}).get("multipliers"),
            "kkt_run": cert.get("kkt", {}).get("run_value"),
            "force_imbalance": s.get("force_imbalance"),  # the KKT residual over the contact forces
            "w_change": cert.get("settled", {}).get("value"),
            "stderr": stderr.strip().splitlines()[-1:] if returncode not in (0, 4) else []}


def fmt(v, spec):
    return format(v, spec) if isinstance(v, (int, float)) else "-"


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", default="500,2000")
    ap.add_argument("--seeds", default="0-2")
    ap.add_argument("--dim", type=int, default=2)
    ap.add_argument("--ranks", type=int, default=1)
    ap.add_argument("--max-iter", type=int, default=40000)
    ap.add_argument("--timeout", type=float, default=3600)
    ap.add_argument("--set", action="append", default=[])
    ap.add_argument("--json")
    args = ap.parse_args()
    ns = [int(float(x)) for x in args.n.split(",")]
    seeds = seeds_of(args.seeds)
    print(f"{'N':>7} {'dim':>3} {'seed':>4} {'exit':>4} {'cert':>5} {'iters':>6} {'s':>7} {'expl':>5} "
          f"{'W/N^2':>8} {'overlap':>9} {'KKT':>9}", flush=True)
    rows = []
    for n in ns:
        for seed in seeds:
            r = run_one(n, seed, args)
            rows.append(r)
            print(f"{n:>7} {args.dim:>3} {seed:>4} {r['exit']:>4} {str(bool(r['converged'])):>5} "
                  f"{fmt(r['iterations'], '>6')} {fmt(r['seconds'], '>7.1f')} {fmt(r['explosion_iterations'], '>5')} "
                  f"{fmt(r['W_over_N2'], '>8.5f')} {fmt(r['max_overlap'], '>9.2e')} {fmt(r['kkt'], '>9.2e')}"
                  + (f"  {r['stderr'][0]}" if r["stderr"] else ""), flush=True)
            if args.json:
                with open(args.json, "a") as f:
                    f.write(json.dumps(r) + "\n")
    print("\nsummary: N, certified/runs, median iterations and seconds of the certified runs")
    for n in ns:
        rs = [r for r in rows if r["n"] == n]
        ok = [r for r in rs if r["converged"]]
        med_it = statistics.median(r["iterations"] for r in ok) if ok else None
        med_s = statistics.median(r["seconds"] for r in ok) if ok else None
        print(f"  N = {n}: {len(ok)}/{len(rs)} certified; median {fmt(med_it, '.0f')} iterations, "
              f"{fmt(med_s, '.1f')} s")


if __name__ == "__main__":
    main()
