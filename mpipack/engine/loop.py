"""The one loop: iterate a scene until its stop rule, running hooks on their schedules.

    set-up      Solver(scene).initialise(source): particles, partition, ghosts, rows
    per iteration
      step      solver.step(): the method's iteration (``methods``), ONE reduction
      hooks     whatever is due: progress, output, metrics, the wall-time limit (``hooks``)
      stop      the stop rule's decision (``stop.rule``): certified, eps, max_iter,
                max_seconds, a signal, a hook's request; the watchdog's verdict
    stopped     at_stop hooks (the checkpoint of a signal, the wall time or a bound)
    end         final figures, the certificate, the result
"""

import math
import time

from mpipack.engine import hooks as hooks_mod
from mpipack.engine.solver import Solver
from mpipack.engine.timers import HOOKS, PhaseTimers, format_report, process_age_seconds
from mpipack.stop.rule import StopRule


def run(scene, comm, hooks=(), source=None, solver=None, profile=False):
    """Iterate a scene until its stop rule.

    scene: a config.Scene (its ``stop`` section is the stop rule); hooks: ``hooks.Hook``s;
    source: a BlockState to start from instead of the scene's initial data; solver: continue
    an existing Solver (its physics stays; only the stop rule comes from ``scene``).
    Returns (solver, result dict): "converged" is true only when the final state meets the
    certificate, "stop_reason" says what stopped the loop (``stop.rule``). With ``profile``
    the result has the phase table.
    """
    timers = solver.timers if solver is not None else PhaseTimers()
    t0 = time.perf_counter()
    if solver is None:
        solver = Solver(scene, comm, timers)
        solver.initialise(source)
    setup_seconds = time.perf_counter() - t0
    rule = solver.stop_rule = StopRule(scene, solver, source.extra if source is not None else None)
    ctx = hooks_mod.Context(solver)
    start_iter = solver.state.iteration
    start_inner = solver.counters["inner_iterations"]
    # the wall clock of the run's figures (max_seconds, the wall-time limit) starts here; the
    # loop's own seconds (loop_seconds, the profile) after the at_start hooks (the snapshot of
    # iteration 0: output, as the final one is; at_start_seconds)
    t_start = solver.clock0 = time.perf_counter()
    for h in hooks:
        if h.at_start:
            h(ctx)
    t_loop = time.perf_counter()
    timers.start()
    first_iteration = math.nan
    reason = rule.before(solver)
    while reason is None:
        fig = solver.step()
        if first_iteration != first_iteration:  # NaN until the first iteration is done
            first_iteration = process_age_seconds()
        ctx.iteration, ctx.figures, ctx.elapsed = fig["iteration"], fig, fig["wall"]
        asked = None
        for h in hooks:
            if h.due(ctx.iteration, ctx.elapsed) and h(ctx) == hooks_mod.STOP:
                asked = h.name
        reason = ctx.stop_reason = rule.decide(solver, fig, asked)
        timers.lap(HOOKS)
    ctx.stop_reason = reason
    loop_seconds = time.perf_counter() - t_loop
    timers.stop()
    for h in hooks:  # e.g. the checkpoint of a stop: the state as the loop left it
        if h.at_stop:
            h(ctx)
    final = solver.finish()
    certificate = rule.final(solver, final, reason)
    # the KKT residual reported is the certificate's (the best multipliers' when they were
    # fitted); the run's own multipliers' beside it (the force imbalance is theirs)
    final["kkt_residual_run"] = final["kkt_residual"]
    final["kkt_residual"] = certificate["kkt"]["value"]
    iters = solver.state.iteration - start_iter
    inner = solver.counters["inner_iterations"] - start_inner
    # work: particle-iterations of the kernel, inner ones for the nested methods
    work = solver.n * solver.method.work(iters, inner)
    result = {
        "iterations": solver.state.iteration,
        # the packing meets every tolerance of the certificate (whatever stopped the loop)
        "converged": all(c["ok"] for c in certificate.values()),
        "certificate": certificate,
        "stop_reason": reason,
        "relative_change": ctx.figures.get("relative_change", math.nan),
        "setup_seconds": setup_seconds,
        "at_start_seconds": t_loop - t_start,
        "loop_seconds": loop_seconds,
        # from the start of the process (interpreter, imports, numba cache, set-up) to the
        # end of the first iteration of this loop
        "first_iteration_seconds": first_iteration,
        "particle_iterations_per_second": work / loop_seconds if loop_seconds > 0 else 0.0,
        **final,
        **solver.counters,
    }
    summary = solver.method.summary()
    if summary is not None:
        result["schedule"] = summary
    if profile:
        result["profile"] = timers.report(comm, loop_seconds)
    ctx.result = result
    for h in hooks:
        if h.at_end:
            h(ctx)
    return solver, result


def profile_lines(result):
    """The phase table of a run with profile=True, as text lines."""
    return format_report(result["profile"])
