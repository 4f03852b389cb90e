"""Command line: ``mpipack run | bench | scenes``. Thin dispatch; the work is elsewhere.

Exit codes (the same on every rank):
    0  done: converged, or ran the requested iterations (stop.eps = 0)
    1  internal error (a bug: please report it with the traceback)
    2  bad input (scene, option): one line naming the key
    3  numerical trouble: NaN, Inf or divergence in the state
    4  not converged within stop.max_iter
"""

import argparse
import json
import os
import sys
import time

EXIT_OK, EXIT_INTERNAL, EXIT_INPUT, EXIT_NUMERICAL, EXIT_NOT_CONVERGED = 0, 1, 2, 3, 4


def _world_rank():
    """This process's rank under mpirun/srun, read from the launcher's environment (mpi4py is
    not imported to parse arguments)."""
    for var in ("OMPI_COMM_WORLD_RANK", "PMIX_RANK", "PMI_RANK", "SLURM_PROCID"):
        v = os.environ.get(var)
        if v is not None and v.isdigit():
            return int(v)
    return 0


class _Parser(argparse.ArgumentParser):
    """argparse that prints usage errors on rank 0 only (every rank still exits with code 2)."""

    def error(self, message):
        if _world_rank() == 0:
            self.print_usage(sys.stderr)
            print(f"{self.prog}: error: {message}", file=sys.stderr, flush=True)
        sys.exit(EXIT_INPUT)

    def print_help(self, file=None):
        if _world_rank() == 0:
            super().print_help(file)


def _count(text):
    """A positive whole number, also written as 1e6."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not (v == v and v >= 1 and v < 1e15 and v == int(v)):
        raise argparse.ArgumentTypeError(f"must be a positive whole number, got {text!r}")
    return int(v)


def _dimension(text):
    if text not in ("1", "2", "3"):
        raise argparse.ArgumentTypeError(f"must be 1, 2 or 3, got {text!r}")
    return int(text)


def _parser():
    p = _Parser(prog="mpipack", description="Dense sphere packings with the damped Arrow-Hurwicz algorithm, on MPI ranks.")
    sub = p.add_subparsers(dest="command", required=True)
    r = sub.add_parser("run", help="run a scene (default: the paper's section 4.3 case)")
    r.add_argument("scene", nargs="?", default=None, help="a TOML file or a built-in scene name (mpipack scenes)")
    r.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a scene key, e.g. --set method.alpha=0.01 (repeatable)")
    r.add_argument("--out", default=None, help="output folder (default mpipack-out/<scene>)")
    r.add_argument("--seed", type=int, default=None, help="random seed of the initial data")
    r.add_argument("--quiet", action="store_true", help="no progress lines")
    r.add_argument("--dump", default=None, metavar="FILE.npz",
                   help="also write the final particles and lambda > 0 pairs, in gid order (gathered on rank 0; for tests and small N)")
    r.add_argument("--profile", action="store_true",
                   help="print the time per phase of the loop (max and mean over ranks) at the end; also in summary.json")
    b = sub.add_parser("bench", help="throughput and memory benchmark in a packed state")
    b.add_argument("--dim", type=_dimension, action="append", default=None, help="dimension (repeatable; default 2 and 3)")
    b.add_argument("--n", type=_count, action="append", default=None, help="particle count (repeatable; default 1e4 1e5 1e6)")
    b.add_argument("--iters", type=_count, default=None, help="timed iterations (default: about 3 s of work)")
    b.add_argument("--form", default="S", choices=["S", "NS"])
    b.add_argument("--json", default=None, help="append result rows to this JSON-lines file")
    pp = sub.add_parser("paper", help="re-run the paper's experiments; writes report.md and PNG figures")
    pp.add_argument("--quick", action="store_true", help="a reduced run (under a minute)")
    pp.add_argument("--out", default=None, help="output folder (default mpipack-out/paper[-quick])")
    sub.add_parser("scenes", help="list the built-in scenes")
    return p


def _fail(comm, code, message):
    """Exit every rank with ``code``; rank 0 prints the one-line message."""
    if comm is None or comm.rank == 0:
        print(f"mpipack: error: {message}", file=sys.stderr, flush=True)
    sys.stdout.flush()
    sys.exit(code)


def main(argv=None):
    args = _parser().parse_args(argv)
    if args.command == "scenes":
        from . import config
        for name in config.builtin_names():
            print(name)
        return 0
    if args.command == "paper":
        if args.out is not None and os.path.exists(args.out) and not os.path.isdir(args.out):
            _fail(None, EXIT_INPUT, f"--out: {args.out} exists and is not a folder")
        from .experiments import paper
        return paper.main(args)
    if args.command == "bench":
        from . import bench
        return bench.main(args)
    return run_command(args)


def run_command(args):
    from . import config
    from .comm import Comm
    comm = Comm()
    # every rank validates the same input; the verdict is shared so that all exit together
    try:
        scene = config.load(args.scene, args.overrides, args.seed)
        err = None
    except config.SceneError as e:
        scene, err = None, str(e)
    errs = comm.allgather_object(err)
    first = next((e for e in errs if e), None)
    if first:
        _fail(comm, EXIT_INPUT, first)
    out = args.out or scene.output.dir or os.path.join("mpipack-out", scene.name)
    # output locations are checked before any work, so a bad path costs nothing
    err = None
    if comm.rank == 0:
        err = _prepare_outputs(out, args.dump)
    err = comm.bcast_object(err)
    if err:
        _fail(comm, EXIT_INPUT, err)
    try:
        return _run(comm, scene, out, args)
    except SystemExit:
        raise
    except BaseException:
        import traceback
        traceback.print_exc()
        sys.stderr.flush()
        if comm.size > 1:
            comm.abort(EXIT_INTERNAL)
        return EXIT_INTERNAL


def _prepare_outputs(out, dump):
    """Create the output folder (and the dump file's folder); a one-line error or None."""
    if dump is not None:
        if not dump.endswith(".npz"):
            return f"--dump expects a file name ending in .npz, got {dump!r}"
        if os.path.isdir(dump):
            return f"--dump: {dump} is a folder"
    for folder, what in ((out, "--out"), (os.path.dirname(os.path.abspath(dump)) if dump else None, "--dump")):
        if folder is None:
            continue
        if os.path.exists(folder) and not os.path.isdir(folder):
            return f"{what}: {folder} exists and is not a folder"
        try:
            os.makedirs(folder, exist_ok=True)
        except OSError as e:
            return f"{what}: cannot create folder {folder}: {e.strerror}"
        if not os.access(folder, os.W_OK):
            return f"{what}: folder {folder} is not writable"
    return None


def _run(comm, scene, out, args):
    from . import hooks as hooks_mod
    from . import solver as solver_mod
    rank0 = comm.rank == 0
    m = scene.method
    every = scene.output.progress_every
    show = rank0 and not args.quiet and every > 0
    if show:
        print(f"mpipack: scene {scene.name}: {m.name.upper()}-{m.form} dim={scene.dim} "
              f"N={scene.n} on {comm.size} rank(s); alpha={m.alpha:g} beta={m.beta:g} "
              f"gamma={m.gamma:g} c={m.c:g} eps={scene.stop.eps:g}", flush=True)
        print(f"{'iteration':>10} {'rel.change':>11} {'max overlap':>11} {'contacts':>9} {'it/s':>9}", flush=True)
    hooks = [hooks_mod.progress_printer(scene, comm, every)] if show else []
    if scene.output.metrics_every > 0:
        hooks.append(hooks_mod.metrics_recorder(scene, comm, os.path.join(out, "metrics.csv"),
                                                scene.output.metrics_every))
    t0 = time.perf_counter()
    try:
        solver, res = solver_mod.run(scene, comm, hooks=hooks, profile=args.profile)
    except solver_mod.NumericalError as e:
        _fail(comm, EXIT_NUMERICAL, str(e))
    except solver_mod.TooDenseError as e:
        _fail(comm, EXIT_INPUT, str(e))
    wall = time.perf_counter() - t0
    summary = {
        "scene": scene.name, "method": m.name, "form": m.form, "dim": scene.dim,
        "n": scene.n, "ranks": comm.size, "iterations": res["iterations"],
        "converged": res["converged"], "stop_reason": res["stop_reason"],
        "stop_rule": scene.stop.rule, "certificate": res["certificate"], "wall_seconds": wall,
        "relative_change": res["relative_change"], "max_overlap": res["max_overlap"],
        "W": res["W"], "kkt_residual": res["kkt_residual"], "complementarity": res["complementarity"],
        "density": res["density"] if _density_valid(scene, res) else None,
        "density_radius": res["density_radius"],
        "particle_iterations_per_second": res["particle_iterations_per_second"],
        "particle_iterations_per_second_per_rank": res["particle_iterations_per_second"] / comm.size,
        "loop_seconds": res["loop_seconds"], "setup_seconds": res["setup_seconds"],
        "first_iteration_seconds": res["first_iteration_seconds"],
        "active_pairs": res["active_pairs"], "rebuilds": res["rebuilds"],
        "rebalances": res["rebalances"], "far_ghosts": res["far_ghosts"],
        "max_imbalance": res["max_imbalance"], "inner_iterations": res["inner_iterations"],
        "parameters": {k: getattr(m, k) for k in ("alpha", "beta", "gamma", "c", "l_inner", "eps_inner", "tau")},
        "eps": scene.stop.eps, "max_iter": scene.stop.max_iter, "seed": scene.seed,
    }
    if args.profile:
        summary["profile"] = res["profile"]
    if args.dump:
        data = solver.gather()
        if rank0:
            import numpy as np
            np.savez(args.dump, **data)
    if rank0:
        with open(os.path.join(out, "summary.json"), "w") as f:
            json.dump(summary, f, indent=2)
            f.write("\n")
        if not args.quiet:
            print(f"mpipack: {_verdict(scene, res)} after {res['iterations']} iterations in {wall:.2f} s "
                  f"({res['particle_iterations_per_second']:.3g} particle-iterations/s)\n"
                  f"  {_certificate_line(res['certificate'])}\n"
                  f"  relative change {res['relative_change']:.3e}, W = {res['W']:.10g}\n"
                  f"  {_density_line(scene, res)}\n"
                  f"  summary: {os.path.join(out, 'summary.json')}", flush=True)
        if args.profile:
            print("mpipack: time per phase of the loop", flush=True)
            for line in solver_mod.profile_lines(res):
                print("  " + line, flush=True)
    return _exit_code(scene, res)


def _density_valid(scene, res):
    """A density is a packing's only when the spheres do not overlap beyond the tolerance (the
    covered measure counts an overlap twice) and it is at most 1."""
    return res["max_overlap"] <= scene.stop.overlap and res["density"] <= 1.0


def _density_line(scene, res):
    if _density_valid(scene, res):
        return (f"packing density {res['density']:.4f} in the ball of radius {res['density_radius']:.3g} "
                f"(radius of gyration) about the centre of mass")
    return (f"packing density not reported: the spheres overlap by up to {res['max_overlap']:.3g} d "
            f"(tolerance {scene.stop.overlap:g}), so the covered measure is not a packing's")


def _verdict(scene, res):
    if res["converged"]:
        return "converged (certified)"
    if scene.stop.rule == "eps" and res["stop_reason"] == "eps":
        return "stopped by (4.3), NOT certified"
    if scene.stop.rule == "eps" and scene.stop.eps == 0:
        return "ran the requested iterations, not certified"
    return "NOT converged"


def _certificate_line(cert):
    names = {"overlap": "max overlap {v:.3e} d", "kkt": "KKT residual {v:.3e}",
             "settled": "W change over the window {v:.3e}"}
    parts = [names[k].format(v=c["value"]) + (" ok" if c["ok"] else f" > {c['tol']:g}")
             for k, c in cert.items()]
    return "certificate: " + ", ".join(parts)


def _exit_code(scene, res):
    """0 when certified; under the paper's rule (stop.rule = "eps") also when (4.3) fired, or
    when stop.eps = 0 asked for a fixed number of iterations; 4 otherwise."""
    if res["converged"]:
        return EXIT_OK
    if scene.stop.rule == "eps" and (scene.stop.eps == 0 or res["stop_reason"] == "eps"):
        return EXIT_OK
    return EXIT_NOT_CONVERGED


if __name__ == "__main__":
    sys.exit(main())
