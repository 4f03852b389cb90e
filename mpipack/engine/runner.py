"""One run of a scene and everything around the loop: the scene (or a restart), the output
folder, the hooks (progress, metrics, snapshots, checkpoints, wall-time limit), signals, and a
summary.json on every exit. ``mpipack run`` (``cli``) and ``mpipack.run`` (``api``) both come
here with a ``RunRequest``; ``engine.loop.run`` iterates. Exit codes: ``mpipack.errors``.

Nothing is lost: output paths are checked before any work; summary.json is written on every
exit (or, if the folder has become unwritable, to a fallback file whose path is printed); a
signal or a numerical failure leaves a checkpoint of the last good state.
"""

import dataclasses
import datetime
import json
import math
import os
import sys
import time

from mpipack import __version__
from mpipack.errors import (EXIT_CHECKPOINTED, EXIT_INPUT, EXIT_INTERNAL, EXIT_MEANING, EXIT_NOT_CONVERGED,
                            EXIT_NUMERICAL, EXIT_OK, InputError, NumericalError, TooDenseError)

# stop reasons of a run that reached its bound before its certificate (exit 4, checkpointed)
BOUND_STOPS = ("max_iter", "max_seconds")


@dataclasses.dataclass
class RunRequest:
    """What a run is asked to do (``mpipack run``'s options, or ``mpipack.run``'s arguments).

    scene: a built-in name, a TOML path, or None (the default scene); overrides: "key=value"
    strings (``--set``); settings: {dotted key: value} (the library's keyword overrides);
    out: the run folder (None: the scene's output.dir, else mpipack-out/<scene>, numbered when it
    holds a run; with restart alone, the restarted run's folder); overwrite: replace the run an
    explicit folder holds (``choose_run_folder``);
    files: False writes no file at all (no folder, summary, snapshot or checkpoint).
    """
    scene: object = None
    overrides: tuple = ()
    settings: dict = dataclasses.field(default_factory=dict)
    seed: int = None
    out: str = None
    dump: str = None
    quiet: bool = False
    profile: bool = False
    restart: str = None
    walltime: str = None
    overwrite: bool = False
    silent: bool = False
    files: bool = True
    hooks: tuple = ()


@dataclasses.dataclass
class Outcome:
    """How a run ended: the exit code, the one-line error (codes 2 and 3), the summary (what
    summary.json holds), the loop's result dict (None when the loop did not end normally) and
    the path summary.json was written to (None: not written)."""
    code: int
    message: str = None
    summary: dict = None
    result: dict = None
    summary_path: str = None
    solver: object = None  # the engine's Solver at the end (gathers for the library API)


def parse_walltime(text):
    """Seconds from 'HH:MM:SS', 'MM:SS' or seconds; InputError otherwise."""
    try:
        parts = [float(p) for p in text.split(":")]
    except ValueError:
        parts = []
    if not 1 <= len(parts) <= 3 or any(not math.isfinite(p) or p < 0 for p in parts):
        raise InputError(f"--walltime expects HH:MM:SS, got {text!r}")
    seconds = 0.0
    for p in parts:
        seconds = 60.0 * seconds + p
    if seconds <= 0:
        raise InputError(f"--walltime must be positive, got {text!r}")
    return seconds


def resolve_scene(comm, args):
    """(scene, restart BlockState or None). A restart takes its scene from the checkpoint;
    a scene or --set given beside it may change only config.RESTART_MAY_CHANGE."""
    from mpipack import config
    if isinstance(args.scene, config.Scene):  # a Scene object (the library API)
        table, source = args.scene.as_dict(), None
    else:
        table, source = None, args.scene
    settings = getattr(args, "settings", None) or {}
    if not args.restart:
        return config.load(source, args.overrides, args.seed, base=table, settings=settings), None
    from mpipack.io.checkpoint import CheckpointError
    from mpipack.engine.output import read_state
    try:
        state, table, _ = read_state(comm, args.restart)
    except CheckpointError as e:
        raise InputError(str(e)) from None
    if isinstance(table, str):
        table = json.loads(table)
    scene = config.load(source, args.overrides, args.seed, base=table, settings=settings)
    changed = config.physics_changes(table, scene.as_dict())
    if changed:
        raise InputError(f"--restart: the scene changes {', '.join(changed[:3])}; only "
                         f"{', '.join(k + ('.*' if k != 'name' else '') for k in config.RESTART_MAY_CHANGE)} "
                         f"may change on a restart")
    return scene, state


def restart_record(args, scene, state):
    """What a restart took from its checkpoint and what it was told (summary.json's
    ``restart``): the iteration, the --set keys given now, and the settings of the checkpoint's
    scene it keeps that differ from the defaults (stop.*, output.*, neighbor.*), so that nothing
    is inherited silently."""
    import copy

    from mpipack import config
    given = {str(o).split("=", 1)[0].strip() for o in args.overrides} | set(getattr(args, "settings", None) or {})
    now = scene.as_dict()
    fresh = copy.deepcopy(now)  # the same scene with these sections as a new run resolves them
    for section in ("stop", "output", "neighbor"):
        fresh[section] = copy.deepcopy(config.DEFAULTS[section])
    fresh = config.load(None, (), None, base=fresh).as_dict()
    inherited = {f"{section}.{key}": value for section in ("stop", "output", "neighbor")
                 for key, value in now[section].items()
                 if f"{section}.{key}" not in given and value != fresh[section][key]}
    return {"from": args.restart, "iteration": state.iteration, "overrides": sorted(given),
            "inherited": inherited}


# what makes a folder a run's (``engine.output``, ``mpipack vtk``)
RUN_FILES = ("summary.json", "checkpoint.h5", "snapshots.h5", "snapshots.xmf", "metrics.csv",
             "snapshots.pvd", "vtk")
# made from a run's files (ParaView's index of the contacts, its script and the container's
# surface, mpipack post and export): removed with the run they were made from by --overwrite, not a run by themselves
DERIVED_FILES = ("snapshots_contacts.xmf", "snapshots_contacts.pvd", "view.py", "container.vtu", "post",
                 "export")


def run_files(folder):
    """The run files a folder holds (none when it does not exist)."""
    return [f for f in RUN_FILES if os.path.lexists(os.path.join(folder, f))]


def choose_run_folder(args, scene):
    """(folder, one-line error or None, a note for the user or None): where this run writes.

    A run never writes into a folder that holds another run. ``--restart`` alone continues its
    run in place; an explicit folder (``--out``, or the scene's output.dir) that holds another
    run is refused unless ``--overwrite`` (which removes the old run's files first); the default
    folder, mpipack-out/<scene>, is numbered instead (mpipack-out/<scene>-2, -3, ...)."""
    overwrite = getattr(args, "overwrite", False)
    restart_dir = None
    if args.restart:
        restart_dir = args.restart if os.path.isdir(args.restart) else os.path.dirname(os.path.abspath(args.restart))
    explicit = args.out or scene.output.dir
    if explicit is None and restart_dir is not None:
        if overwrite:
            return None, "--overwrite would remove the checkpoint that --restart continues; give --out", None
        return restart_dir, None, None  # the one way to continue a run in place
    if explicit is None:
        base = os.path.join("mpipack-out", scene.name)
        folder, k = base, 1
        while run_files(folder):
            k += 1
            folder = f"{base}-{k}"
        note = f"{base} holds an earlier run: this one writes to {folder}" if k > 1 else None
        return folder, None, note
    held = run_files(explicit)
    if restart_dir is not None and os.path.realpath(explicit) == os.path.realpath(restart_dir):
        if overwrite:
            return None, "--overwrite would remove the checkpoint that --restart continues", None
        return explicit, None, None
    if held and not overwrite:
        return None, (f"--out {explicit} holds another run ({', '.join(held)}): continue it with "
                      f"--restart {explicit}, replace it with --overwrite, or choose another --out"), None
    if held:
        import shutil
        held += [f for f in DERIVED_FILES if os.path.lexists(os.path.join(explicit, f))]
        try:
            for f in held:
                path = os.path.join(explicit, f)
                shutil.rmtree(path) if os.path.isdir(path) and not os.path.islink(path) else os.remove(path)
        except OSError as e:
            return None, f"--overwrite: cannot remove {path}: {e.strerror}", None
        return explicit, None, f"--overwrite: removed the earlier run's {', '.join(held)} from {explicit}"
    return explicit, None, None


def prepare_outputs(out, dump):
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
    summary = os.path.join(out, "summary.json")
    if os.path.isdir(summary):
        return f"--out: {summary} is a folder"
    return None


def walltime_hook(comm, limit, checkpoints, n, dim):
    """Stop (and checkpoint) before ``limit`` seconds of the process have passed: the margin is
    twice the last checkpoint's write time (before the first one, 0.25 s plus the state's size
    at 50 MB/s), 10 iterations and 1 s. Every input is the same on every rank: a collective
    decision."""
    from mpipack.engine.hooks import STOP, Hook
    from mpipack.engine.timers import process_age_seconds
    first_estimate = 0.25 + n * (3 * dim + 2) * 8 / 50e6
    state = {"offset": None, "t": 0.0, "it": 0, "per_it": 0.0}

    def start(ctx):  # seconds of the process before the loop began, rank 0's
        state["offset"] = comm.bcast_object(process_age_seconds())
        state["it"] = ctx.iteration

    def check(ctx):
        dt, dn = ctx.elapsed - state["t"], ctx.iteration - state["it"]
        if dn > 0:
            state["per_it"] = max(state["per_it"] * 0.9, dt / dn)
        state["t"], state["it"] = ctx.elapsed, ctx.iteration
        write = checkpoints.last_seconds if checkpoints.last_seconds is not None else first_estimate
        margin = 2.0 * write + 10.0 * state["per_it"] + 1.0
        if state["offset"] + ctx.elapsed + margin >= limit:
            return STOP
        return None

    return [Hook(start, at_start=True, name="walltime-start"), Hook(check, every=1, name="walltime")]


def write_summary(out, summary, rank0):
    """summary.json in the run folder; if that fails, a fallback file (whose path is printed).
    Returns the path written, or None on other ranks."""
    if not rank0:
        return None
    text = json.dumps(summary, indent=2, default=_json_default) + "\n"

    def write(target):
        with open(target + ".tmp", "w") as f:
            f.write(text)
        os.replace(target + ".tmp", target)

    return write_with_fallback(write, [os.path.join(out, "summary.json"),
                                       os.path.join(os.getcwd(), f"mpipack-summary-{os.getpid()}.json"),
                                       os.path.join("/tmp", f"mpipack-summary-{os.getpid()}.json")],
                               "the summary")


def write_with_fallback(write, targets, what):
    """write(target) for the first target that works; a warning per failure, and the path when
    it is not the first one. Returns the path written, or None."""
    for target in targets:
        try:
            write(target)
        except OSError as e:
            print(f"mpipack: warning: cannot write {target}: {e.strerror or e}", file=sys.stderr, flush=True)
            continue
        if target != targets[0]:
            print(f"mpipack: {what}: written to {target} instead", file=sys.stderr, flush=True)
        return target
    return None


def _json_default(o):
    try:
        import numpy as np
        if isinstance(o, np.generic):
            return o.item()
        if isinstance(o, np.ndarray):
            return o.tolist()
    except ImportError:
        pass
    return str(o)


def base_summary(comm, scene, args):
    return {"scene": scene.name, "method": scene.method.name, "form": scene.method.form,
            "dim": scene.dim, "n": scene.n, "ranks": comm.size, "seed": scene.seed,
            "version": __version__, "date": datetime.datetime.now().astimezone().isoformat(timespec="seconds"),
            "command_line": sys.argv, "restart_from": args.restart,
            "parameters": {k: getattr(scene.method, k) for k in
                           ("alpha", "beta", "gamma", "c", "schedule", "l_inner", "eps_inner", "tau")},
            "stop_rule": scene.stop.rule, "eps": scene.stop.eps, "max_iter": scene.stop.max_iter,
            "resolved_scene": scene.as_dict()}


def execute(comm, args):
    """One ``mpipack run`` on every rank of ``comm``; returns the exit code (the same on every
    rank). Prints on rank 0 only."""
    return run_request(comm, args).code


def run_request(comm, args):
    """One run on every rank of ``comm`` (args: a ``RunRequest``); returns its ``Outcome``."""
    from mpipack import config
    from mpipack.stop.signals import install_handlers, restore_handlers
    rank0 = comm.rank == 0
    err, scene, state, walltime = None, None, None, None
    try:
        walltime = parse_walltime(args.walltime) if args.walltime else None
        scene, state = resolve_scene(comm, args)
    except (config.SceneError, InputError) as e:
        err = str(e)
    errs = comm.allgather_object(err)
    first = next((e for e in errs if e), None)
    if first:
        return Outcome(fail(comm, EXIT_INPUT, first), first)
    files = getattr(args, "files", True)
    out = None
    if files:
        # rank 0 looks at the file system and decides; every rank takes its word
        out, err, note = choose_run_folder(args, scene) if rank0 else (None, None, None)
        if err is None and rank0:
            err = prepare_outputs(out, args.dump)
        out, err, note = comm.bcast_object((out, err, note))
        if err:
            return Outcome(fail(comm, EXIT_INPUT, err), err)
        if note and rank0 and not args.quiet:
            print(f"mpipack: {note}", flush=True)
    previous = install_handlers()
    try:
        return _execute(comm, args, scene, state, out, walltime)
    except SystemExit:
        raise
    except BaseException as e:  # a bug: keep what can be kept, then abort the job
        import traceback
        traceback.print_exc()
        sys.stderr.flush()
        summary = {**base_summary(comm, scene, args), "exit_code": EXIT_INTERNAL,
                   "exit_status": EXIT_MEANING[EXIT_INTERNAL], "error": repr(e)}
        path = write_summary(out, summary, rank0) if out is not None else None
        if comm.size > 1:
            comm.abort(EXIT_INTERNAL)
        return Outcome(EXIT_INTERNAL, repr(e), summary, None, path)
    finally:
        restore_handlers(previous)


def fail(comm, code, message):
    """Rank 0 prints the one-line error; every rank returns ``code``."""
    if comm is None or comm.rank == 0:
        print(f"mpipack: error: {message}", file=sys.stderr, flush=True)
    sys.stdout.flush()
    return code


def _execute(comm, args, scene, state, out, walltime):
    """The run itself, once its scene, state and folder are ready (``out`` None: no files)."""
    from mpipack.engine import hooks as hooks_mod
    from mpipack.engine import output
    from mpipack.engine.loop import run
    rank0 = comm.rank == 0
    m = scene.method
    every = scene.output.progress_every
    show = rank0 and not args.quiet and every > 0
    start_iter = state.iteration if state is not None else 0
    if show:
        print(f"mpipack: scene {scene.name}: {m.name.upper()}-{m.form} dim={scene.dim} "
              f"N={scene.n} on {comm.size} rank(s); "
              + ("schedule fire-al (parameters from N, b, d)" if m.schedule == "fire-al" else
                 f"alpha={m.alpha:g} beta={m.beta:g} gamma={m.gamma:g} c={m.c:g}")
              + f"; stop: {scene.stop.rule}"
              + (f"; restart from iteration {start_iter}" if state is not None else ""), flush=True)
        print(f"{'iteration':>10} {'rel.change':>11} {'max overlap':>11} {'contacts':>9} {'it/s':>9}", flush=True)
    hooks = [hooks_mod.progress_printer(scene, comm, every)] if show else []
    hooks += list(getattr(args, "hooks", ()))
    if out is None:  # no files: a scene's file outputs are off
        scene = scene.replace(output={"metrics_every": 0, "snapshots": False, "checkpoint_every": 0})
    metrics = None
    if scene.output.metrics_every > 0:
        metrics = hooks_mod.metrics_recorder(scene, comm, os.path.join(out, "metrics.csv"),
                                             scene.output.metrics_every,
                                             resume_after=start_iter if state is not None else None)
        hooks.append(metrics)
    snapshots = None
    if scene.output.snapshots:
        snapshots = output.Snapshots(scene, comm, out, scene.output.snapshot_every,
                                     truncate_after=start_iter if state is not None else None)
        hooks += snapshots.hooks()
    checkpoints = output.Checkpoints(scene, comm, out, scene.output.checkpoint_every) if out else output.NoCheckpoints()
    hooks += checkpoints.hooks()
    if walltime is not None:
        hooks += walltime_hook(comm, walltime, checkpoints, scene.n, scene.dim)
    summary = base_summary(comm, scene, args)
    if state is not None:
        summary["restart"] = restart_record(args, scene, state)
        if rank0 and state.iteration >= scene.stop.max_iter and not getattr(args, "silent", False):
            print(f"mpipack: the checkpoint is at iteration {state.iteration}, at or beyond stop.max_iter = "
                  f"{scene.stop.max_iter} (its scene's, kept on a restart): nothing to do; continue with "
                  f"--set stop.max_iter=<larger>", flush=True)
    t0 = time.perf_counter()
    code, message, res, solver = None, None, None, None
    try:
        solver, res = run(scene, comm, hooks=hooks, source=state, profile=args.profile)
    except NumericalError as e:
        code, message, solver = EXIT_NUMERICAL, str(e), e.solver
        summary["trouble"] = e.kind  # "non-finite", "diverged" or "stalled"
        if solver is not None:
            summary["iterations"] = solver.state.iteration
    except TooDenseError as e:
        code, message = EXIT_INPUT, str(e)
    wall = time.perf_counter() - t0
    files = []
    if solver is not None and code == EXIT_NUMERICAL:
        # the last good state: for ParaView and for a look at what went wrong
        checkpoints.safe_write(solver)
        if snapshots is not None:
            snapshots.safe_write(solver, solver.state.iteration, wall, {})
    if res is not None:
        # the checkpoint of a signal, the wall time or a bound was written when the loop
        # stopped (``output.Checkpoints.keeps``), before the final figures
        if res["stop_reason"] in ("signal", "walltime"):
            code = EXIT_CHECKPOINTED
        elif code is None:
            code = exit_code(scene, res)
        summary.update(result_summary(scene, comm, res, wall, args.profile))
        if scene.stop.rule == "jammed":
            summary["jammed"] = jammed_summary(res, solver)
    failed = ((snapshots.failed if snapshots is not None else None) or checkpoints.failed
              or (metrics.failed if metrics is not None else None))
    if failed is not None and code != EXIT_NUMERICAL:
        # a file could not be written (a full disk, a vanished folder): every rank knows it (the
        # writers agree), the run stopped, the previous checkpoint is whole
        code, message = EXIT_INPUT, f"output not written: {failed}"
        summary["output_failed"] = failed
    if checkpoints.last_iteration is not None:
        files.append(checkpoints.path)
        summary["checkpoint"] = {"path": checkpoints.path, "iteration": checkpoints.last_iteration,
                                 "write_seconds": checkpoints.last_seconds}
    if snapshots is not None:
        snapshots.close()
        if snapshots.last_iteration is not None:
            files += [snapshots.path, os.path.splitext(snapshots.path)[0] + ".xmf", snapshots.container_path]
            summary["snapshot_seconds"] = snapshots.seconds
    if args.dump and solver is not None:
        data = solver.gather()
        if rank0:
            files.append(save_dump(args.dump, out or os.getcwd(), data))
    summary.update({"exit_code": code, "exit_status": exit_status(scene, res, code), "error": message,
                    "files": sorted(set(f for f in files if f))})
    path = write_summary(out, summary, rank0) if out is not None else None
    if code in (EXIT_NUMERICAL, EXIT_INPUT):
        return Outcome(fail(comm, code, message), message, summary, res, path, solver)
    if rank0 and not getattr(args, "silent", False):  # --quiet keeps the verdict's line
        print_result(scene, res, wall, path, code, checkpoints, brief=args.quiet)
        if args.profile:
            from mpipack.engine.loop import profile_lines
            print("mpipack: time per phase of the loop", flush=True)
            for line in profile_lines(res):
                print("  " + line, flush=True)
    return Outcome(code, message, summary, res, path, solver)


def save_dump(path, out, data):
    """np.savez of the gathered state; on failure a fallback file in the run folder (or /tmp),
    whose path is printed. Returns the path written."""
    import numpy as np
    return write_with_fallback(lambda target: np.savez(target, **data),
                               [path, os.path.join(out, f"final-{os.getpid()}.npz"),
                                os.path.join("/tmp", f"mpipack-final-{os.getpid()}.npz")],
                               "the final particles")


def result_summary(scene, comm, res, wall, profile):
    from mpipack.engine.report import reported_density
    out = {
        "iterations": res["iterations"], "converged": res["converged"],
        "stop_reason": res["stop_reason"], "certificate": res["certificate"],
        "wall_seconds": wall, "relative_change": res["relative_change"],
        "max_overlap": res["max_overlap"], "W": res["W"], "kkt_residual": res["kkt_residual"],
        # the run's own multipliers' KKT residual (the certificate's may be the fitted ones')
        "kkt_residual_run": res["kkt_residual_run"], "force_imbalance": res["force_imbalance"],
        # where the run's residual sits: the largest net force on one sphere and its share of
        # the squared residual (1/N if spread evenly; snapshots hold net_force per sphere)
        "max_net_force": res["max_net_force"], "net_force_share": res["net_force_share"],
        "complementarity": res["complementarity"], "overlap_A": res["overlap_A"],
        "density": reported_density(scene, res),  # None: not a packing
        "density_measured": res["density"],
        "density_radius": res["density_radius"],
        "particle_iterations_per_second": res["particle_iterations_per_second"],
        "particle_iterations_per_second_per_rank": res["particle_iterations_per_second"] / comm.size,
        "loop_seconds": res["loop_seconds"], "setup_seconds": res["setup_seconds"],
        "at_start_seconds": res["at_start_seconds"],
        "first_iteration_seconds": res["first_iteration_seconds"],
        "active_pairs": res["active_pairs"],
    }
    for k in ("rebuilds", "rebalances", "far_ghosts", "max_imbalance", "inner_iterations"):
        out[k] = res[k]
    # the builds' Verlet skins, in largest diameters (neighbor.adaptive_skin); none yet when only a
    # dense start's build was made (``Solver.rebuild``)
    if res["rebuilds"] and math.isfinite(res["skin_min"]):
        out["skin_range"] = [res["skin_min"], res["skin_max"]]
    if "schedule" in res:
        out["schedule"] = res["schedule"]  # phase reached, its switch, restarts, ALM steps
    if profile:
        out["profile"] = res["profile"]
    return out


def jammed_summary(res, solver):
    """summary.json's ``jammed`` under stop.rule = "jammed": whether the run stopped jammed, the
    verdict in words, and the jammed test's figures at the stop (``stop.rule``: max overlap, W's
    change over its window of iterations and the tolerances; None when it did not stop jammed)."""
    test = solver.stop_rule.jammed if solver is not None and solver.stop_rule is not None else None
    jammed = res["stop_reason"] == "jammed"
    return {"stopped_jammed": jammed, "certified": bool(res["converged"]),
            "status": ("jammed and certified" if res["converged"] else "jammed (not certified)") if jammed
            else None,
            "kkt_residual": res["kkt_residual"], "max_overlap": res["max_overlap"], "W": res["W"],
            "test": test if jammed else None}


def exit_code(scene, res):
    """0 when certified; under the paper's rule (stop.rule = "eps") also when stop.eps = 0 asked
    for a fixed number of iterations, or when (4.3) fired on a feasible configuration (max
    overlap within stop.overlap: (4.3) can fire where nothing moves, e.g. all centres at one
    point); under stop.rule = "jammed" also when the jammed test stopped the run (its overlap
    is within stop.overlap: a packing, what the rule asks for); 4 otherwise."""
    if res["converged"]:
        return EXIT_OK
    if scene.stop.rule == "jammed" and res["stop_reason"] == "jammed":
        return EXIT_OK
    if scene.stop.rule == "eps" and scene.stop.eps == 0:
        return EXIT_OK
    if scene.stop.rule == "eps" and res["stop_reason"] == "eps" and res["certificate"]["overlap"]["ok"]:
        return EXIT_OK
    return EXIT_NOT_CONVERGED


def exit_status(scene, res, code):
    """The words of an exit code in summary.json; exit 0 without a certificate (the paper's rule
    (4.3), or the requested iterations) says so instead of "converged"."""
    if code == EXIT_OK and res is not None and not res["converged"]:
        from mpipack.engine.report import verdict
        return verdict(scene, res).replace("NOT", "not")
    return EXIT_MEANING[code]


def print_result(scene, res, wall, summary_path, code, checkpoints, brief=False):
    """The result on rank 0: the verdict, the certificate, W, the density, what to do next, the
    summary's path; ``brief`` (``--quiet``): the verdict's line alone."""
    from mpipack.engine.report import certificate_line, density_line, residual_line, verdict
    lines = [f"mpipack: {verdict(scene, res)} after {res['iterations']} iterations in {wall:.2f} s "
             f"({res['particle_iterations_per_second']:.3g} particle-iterations/s)",
             f"  {certificate_line(res['certificate'])}",
             f"  relative change {res['relative_change']:.3e}, W = {res['W']:.10g}, force imbalance "
             f"{res['force_imbalance']:.3e} (net force / contact forces)",
             f"  {density_line(scene, res)}"]
    if brief:
        print(lines[0], flush=True)
        return
    if not res["certificate"]["kkt"]["ok"]:
        lines.append(f"  {residual_line(scene, res)}")
    if code == EXIT_CHECKPOINTED:
        lines.append(f"  stopped by {res['stop_reason']}: checkpoint of iteration "
                     f"{checkpoints.last_iteration} in {checkpoints.path}; continue with "
                     f"mpipack run --restart {os.path.dirname(checkpoints.path)}")
    elif (code == EXIT_NOT_CONVERGED and res["stop_reason"] in BOUND_STOPS
          and checkpoints.last_iteration == res["iterations"]):
        bound = "stop.max_iter" if res["stop_reason"] == "max_iter" else "stop.max_seconds"
        lines.append(f"  checkpoint of iteration {checkpoints.last_iteration} in {checkpoints.path}; "
                     f"continue with mpipack run --restart {os.path.dirname(checkpoints.path)} "
                     f"--set {bound}=<larger>")
    if summary_path is not None:
        lines.append(f"  summary: {summary_path}")
    print("\n".join(lines), flush=True)
