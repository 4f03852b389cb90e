"""Is it the fit or the configuration? Runs a scene (on any number of ranks) and, every K
iterations from iteration START, prints the KKT residual of the current configuration with the
run's own multipliers and with the best multipliers >= 0 after long fits: how far the
configuration itself is from balance, against what the certificate's fits (at most 2000 steps,
within their budget) can show.

    [mpirun -n P] python tools/least_kkt_trace.py [SCENE] --set n=32000 --seed 2 \\
        --start 30000 --every 2500 --last 70000 --steps 2000,8000 [--json rows.jsonl]

One JSON row per probe: iteration, max overlap, W, "run" (the run's multipliers), and for each
fit length k "fit<k>" (the least residual met in k FISTA steps from the run's multipliers,
``measures.best_kkt`` with the stall rule relaxed) and "s<k>" (its seconds). The run itself is
the scene's (the probes change nothing in its state), but it does not stop at its certificate
(the stop rule is set to (4.3) with eps = 0, so it runs to --last). docs/research/convergence.md,
section 3o: on 2D N = 32000 seed 2 the configuration was within 1e-2 from about iteration
57500, the certificate fired at 69150.
"""

import argparse
import json
import sys
import time


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene", nargs="?", default=None)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--seed", type=int, default=None)
    ap.add_argument("--start", type=int, default=0, help="first probe at or after this iteration")
    ap.add_argument("--every", type=int, required=True, help="probe every K iterations")
    ap.add_argument("--last", type=int, required=True, help="run to this iteration")
    ap.add_argument("--steps", default="2000,8000", help="fit lengths, comma-separated")
    ap.add_argument("--json", default=None, help="also append the rows to this file")
    args = ap.parse_args(argv)
    steps = [int(k) for k in args.steps.split(",")]
    if args.every < 1 or args.last < 1 or any(k < 1 for k in steps):
        raise SystemExit("least_kkt_trace: --every, --last and --steps must be positive")

    from mpipack import config
    from mpipack.stop import fit, measures
    from mpipack.engine import hooks
    from mpipack.engine import loop
    from mpipack.parallel.comm import Comm

    fit.MAX_STEPS = max(fit.MAX_STEPS, max(steps))
    fit.STALL_GAIN = 1e-4  # a long fit stops only when it no longer moves at all
    overrides = list(args.set) + ['stop.rule="eps"', "stop.eps=0", f"stop.max_iter={args.last}",
                                  "output.snapshot_every=0"]
    scene = config.load(args.scene, overrides, args.seed)
    comm = Comm()
    rows = []

    def probe(ctx):
        if ctx.iteration < args.start:
            return
        s = ctx.solver
        m, _ = measures.measure(s, overlap_a=False)
        row = {"iteration": ctx.iteration, "max_overlap": m["max_overlap"], "W": m["W"],
               "run": m["kkt_residual"]}
        for k in steps:
            t0 = time.perf_counter()
            row[f"fit{k}"], _ = measures.best_kkt(s, m, 0.0, k)
            row[f"s{k}"] = round(time.perf_counter() - t0, 2)
        rows.append(row)
        if comm.rank == 0:
            print(json.dumps(row), flush=True)
            if args.json:
                with open(args.json, "a") as f:
                    f.write(json.dumps(row) + "\n")

    loop.run(scene, comm, hooks=[hooks.Hook(probe, every=args.every)])
    return rows


if __name__ == "__main__":
    main(sys.argv[1:])
