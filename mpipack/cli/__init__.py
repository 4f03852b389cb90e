"""Command line: ``mpipack run | post | export | check | vtk | bench | paper | suite | compare | scenes``. Thin
dispatch: it parses, and the work is elsewhere (``engine.runner`` for run, ``analysis.check``,
``io.vtk``, ``experiments``). Nothing imports this package.

Exit codes (the same on every rank): ``mpipack.errors`` (0 converged, 1 internal error, 2 bad
input, 3 numerical trouble, 4 not converged, 5 stopped with a checkpoint).
"""

import argparse
import os
import sys

from mpipack.errors import EXIT_INPUT, EXIT_OK
from mpipack.parallel.launcher import world_rank as _world_rank


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
    sub = p.add_subparsers(dest="command", required=True, parser_class=_Parser)
    r = sub.add_parser("run", help="run a scene (default: N = 2000 discs, certified)")
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
    r.add_argument("--restart", default=None, metavar="PATH",
                   help="continue from a checkpoint (a checkpoint.h5 or a run folder), on any number of ranks")
    r.add_argument("--walltime", default=None, metavar="HH:MM:SS",
                   help="the job's wall-time limit: checkpoint and exit (code 5) before it")
    r.add_argument("--overwrite", action="store_true",
                   help="replace the run that --out holds (without it, a folder holding another run is refused; "
                        "the default folder is numbered instead)")
    po = sub.add_parser("post", help="measures of a packing from a run's files: density, neighbours, contacts, "
                                     "pressure, gr, order, all, convergence, compare (PNG + JSON + CSV)")
    from mpipack.post.commands import add_arguments as post_arguments
    post_arguments(po)
    ex = sub.add_parser("export", help="a packing as extended XYZ, LAMMPS dump or data, or GSD (OVITO, LAMMPS, HOOMD)")
    ex.add_argument("run", help="a run folder, a snapshots.h5 or a checkpoint.h5")
    ex.add_argument("--format", default="xyz", help="xyz (default), lammps-dump, lammps-data or gsd")
    ex.add_argument("--iteration", type=int, default=None, help="the snapshot of this iteration (default: the last)")
    ex.add_argument("--out", default=None, help="the file to write (default RUN/export/packing-<iteration>.<ext>)")
    v = sub.add_parser("vtk", help="convert a run's snapshots to VTK (.vtu per snapshot + .pvd) for ParaView")
    v.add_argument("run_dir", help="a run folder (holding snapshots.h5)")
    b = sub.add_parser("bench", help="throughput and memory benchmark in a packed state")
    b.add_argument("--dim", type=_dimension, action="append", default=None, help="dimension (repeatable; default 2 and 3)")
    b.add_argument("--n", type=_count, action="append", default=None, help="particle count (repeatable; default 1e4 1e5 1e6)")
    b.add_argument("--iters", type=_count, default=None, help="timed iterations (default: about 3 s of work)")
    b.add_argument("--form", default="S", choices=["S", "NS"])
    b.add_argument("--json", default=None, help="append result rows to this JSON-lines file ('-' with --phases: "
                                                "print them after the tables)")
    b.add_argument("--phases", action="store_true",
                   help="time the phases of a default run (fire-al FIRE, L-BFGS, dual step, metrics, fit) "
                        "per sphere on its packed state, with bytes and MB/s against a measured triad bandwidth")
    b.add_argument("--quick", action="store_true", help="--phases: tiny N, short run, few repetitions (a smoke test)")
    b.add_argument("--run-iters", type=_count, default=None,
                   help="--phases: stop the default run after this many iterations (default: its end)")
    b.add_argument("--repeats", type=_count, default=None, help="--phases: timed repetitions per phase (default 5)")
    b.add_argument("--state-out", default=None, metavar="PREFIX",
                   help="--phases: write each packed state (x, diam) to PREFIX-<dim>d-n<N>.npz (for LAMMPS)")
    b.add_argument("--lammps-json", default=None, metavar="FILE",
                   help="--phases: tools/peers/lammps_fire.py results on those states: ratio to LAMMPS's FIRE step")
    pp = sub.add_parser("paper", help="re-run the paper's experiments; writes report.md and PNG figures")
    pp.add_argument("--quick", action="store_true", help="a reduced run (under a minute)")
    pp.add_argument("--out", default=None, help="output folder (default mpipack-out/paper[-quick])")
    sub.add_parser("scenes", help="list the built-in scenes")
    k = sub.add_parser("check", help="validate a scene and judge it before a run: stability verdict with its "
                                     "margin, overlapping pairs of the start, memory per rank (exit 0 stable, 3 not)")
    k.add_argument("scene", nargs="?", default=None, help="a TOML file or a built-in scene name (mpipack scenes)")
    k.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a scene key, as for run (repeatable)")
    k.add_argument("--seed", type=int, default=None, help="random seed of the initial data")
    k.add_argument("--ranks", type=_count, default=None,
                   help="ranks of the planned run, for the memory per rank (default: this launch's, else 1)")
    st = sub.add_parser("suite", help="run the stiff and extreme cases (each a real mpipack run under mpirun, "
                                      "with a timeout) and write a table of outcomes")
    st.add_argument("--quick", action="store_true", help="a representative subset (under about 2 minutes)")
    st.add_argument("--out", default=None, help="output folder (default mpipack-out/suite[-quick])")
    st.add_argument("--cases", default=None, metavar="NAME,...", help="run only these cases (names as in the table)")
    cp = sub.add_parser("compare", help="work-precision diagrams: error measures against wall time and iterations "
                                        "for several methods, tolerances and seeds (PNG, CSV, markdown)")
    cp.add_argument("scene", nargs="?", default=None, help="a TOML file or a built-in scene name")
    cp.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="override a scene key for every run (repeatable)")
    cp.add_argument("--methods", default=None, metavar="M,...",
                    help="methods, e.g. DAHA-S,NAP-NS,scene or DAHA-S:alpha=0.04:beta=0.15 "
                         "(default: the paper's that apply, plus the scene's own)")
    cp.add_argument("--tolerances", default=None, metavar="EPS,...", help="the ladder of (4.3) tolerances")
    cp.add_argument("--seeds", default=None, metavar="S,...", help="seeds (a list, or a count K for 1..K)")
    cp.add_argument("--peer", action="append", default=[], metavar="[LABEL=]FILE",
                    help="add a peer code's curve: a CSV in compare's format or a tools/peers/lammps_fire.py "
                         "--keep-checks JSON (repeatable; one file per seed)")
    cp.add_argument("--quick", action="store_true", help="N = 7 and N = 100, few seeds (about a minute)")
    cp.add_argument("--out", default=None, help="output folder (default mpipack-out/compare[-quick])")
    return p


def main(argv=None):
    if argv is None and sys.argv[1:2] == ["run"]:
        # at once: a scheduler's signal during the set-up (imports, the numba cache, the
        # scene) stops the run after its first iteration, with a checkpoint and a message
        from mpipack.stop.signals import install_handlers
        install_handlers()
    args = _parser().parse_args(argv)
    if args.command == "scenes":
        from mpipack import config
        for name in config.builtin_names():
            print(name)
        return EXIT_OK
    if args.command == "paper":
        if args.out is not None and os.path.exists(args.out) and not os.path.isdir(args.out):
            if _world_rank() == 0:
                print(f"mpipack: error: --out: {args.out} exists and is not a folder", file=sys.stderr)
            return EXIT_INPUT
        from mpipack.experiments import paper
        return paper.main(args)
    if args.command == "check":
        # its eigenvalue problems are small: one BLAS thread (a shared machine's other jobs make
        # threaded LAPACK 10-30x slower); set before numpy is first imported by this process
        os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
        from mpipack.analysis import check
        return check.main(args, _world_rank())
    if args.command in ("suite", "compare"):
        if args.out is not None and os.path.exists(args.out) and not os.path.isdir(args.out):
            if _world_rank() == 0:
                print(f"mpipack: error: --out: {args.out} exists and is not a folder", file=sys.stderr)
            return EXIT_INPUT
        if args.command == "suite":
            from mpipack.experiments import suite
            return suite.main(args)
        from mpipack.experiments import compare
        return compare.main(args)
    if args.command == "bench":
        from mpipack.experiments import bench
        return bench.main(args)
    from mpipack.parallel.comm import Comm
    comm = Comm()
    if args.command == "vtk":
        return vtk_command(comm, args)
    if args.command == "post":
        from mpipack.post import commands
        return commands.main(comm, args)
    if args.command == "export":
        from mpipack.post import export
        return export.main(comm, args)
    from mpipack.engine import runner
    request = runner.RunRequest(scene=args.scene, overrides=tuple(args.overrides), seed=args.seed,
                                out=args.out, dump=args.dump, quiet=args.quiet, profile=args.profile,
                                restart=args.restart, walltime=args.walltime, overwrite=args.overwrite)
    return runner.execute(comm, request)


def vtk_command(comm, args):
    from mpipack.io.vtk import convert_run
    from mpipack.engine.runner import fail
    try:
        files = convert_run(comm, args.run_dir)
    except (FileNotFoundError, ValueError, OSError) as e:
        return fail(comm, EXIT_INPUT, str(e).splitlines()[0] if str(e) else repr(e))
    if comm.rank == 0:
        print(f"mpipack vtk: {len(files) - 1} snapshot(s) -> {os.path.dirname(files[-1])} "
              f"(open {os.path.basename(files[-1])} in ParaView)", flush=True)
    return EXIT_OK


if __name__ == "__main__":
    sys.exit(main())
