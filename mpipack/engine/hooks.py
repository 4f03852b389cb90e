"""Hooks: what the loop runs besides iterating, each on a schedule (after Dedalus' evaluator
handlers: ``iter=``, ``wall_dt=``).

A hook is a callable ``fn(ctx)`` with a schedule:

    every      run after every K-th iteration (iteration % K == 0)
    wall_dt    run when the loop's wall clock has passed the next multiple of T seconds
    at_start   run once after set-up, before the first iteration (ctx.figures is empty)
    at_stop    run once when the loop has stopped (ctx.stop_reason says why), before the final
               figures touch the state: a checkpoint written here continues the run bit for bit
    at_end     run once after the loop, when the final figures are in ctx.result

The loop calls hooks on every rank at the same iterations: the wall clock it uses is the
maximum over ranks, which travels in the per-iteration reduction, so a wall-time schedule is a
collective decision too. A hook may do collective work (write a file, reduce a metric) and may
ask the loop to stop by returning ``STOP``; it must then decide from values that are the same
on every rank (reduced figures, the iteration count), or the ranks would part ways.

``ctx`` (a ``Context``) gives: solver, iteration, figures (the last iteration's reduced figures),
elapsed (loop wall seconds, the same on every rank), result (at_end only), and ``stop_reason``.
"""

import os

STOP = "stop"


class Context:
    def __init__(self, solver):
        self.solver = solver
        self.iteration = solver.state.iteration
        self.figures = {}
        self.elapsed = 0.0
        self.result = None
        self.stop_reason = None


class Hook:
    def __init__(self, fn, every=None, wall_dt=None, at_start=False, at_stop=False, at_end=False, name=None):
        if every is not None and every < 1:
            raise ValueError("hook 'every' must be >= 1")
        self.fn = fn
        self.every = every
        self.wall_dt = wall_dt if wall_dt else None
        self.at_start = at_start
        self.at_stop = at_stop
        self.at_end = at_end
        self.name = name or getattr(fn, "__name__", "hook")
        self._next_wall = wall_dt if wall_dt else None

    def due(self, iteration, elapsed):
        """True when the schedule fires after this iteration (advances the wall schedule)."""
        fire = self.every is not None and iteration % self.every == 0
        if self._next_wall is not None and elapsed >= self._next_wall:
            fire = True
            # next multiple of wall_dt after now: a slow iteration does not cause a burst
            k = int(elapsed // self.wall_dt) + 1
            self._next_wall = k * self.wall_dt
        return fire

    def __call__(self, ctx):
        return self.fn(ctx)


def progress_printer(scene, comm, every, stream=None):
    """Rank 0 prints iteration, relative change, max overlap, contacts and iterations/s every
    ``every`` seconds of loop time. Returns a Hook (it does nothing on other ranks)."""
    import sys
    out = stream or sys.stdout
    last = {"t": 0.0, "it": 0}

    def progress(ctx):
        if comm.rank != 0:
            return None
        fig = ctx.figures
        dt = max(ctx.elapsed - last["t"], 1e-12)
        rate = (ctx.iteration - last["it"]) / dt
        last["t"], last["it"] = ctx.elapsed, ctx.iteration
        print(f"{ctx.iteration:>10d} {fig['relative_change']:>11.3e} {fig['max_overlap']:>11.3e} "
              f"{fig['active_pairs']:>9d} {rate:>9.0f}", file=out, flush=True)
        return None

    return Hook(progress, wall_dt=every, name="progress")


METRIC_COLUMNS = ("iteration", "wall_seconds", "relative_change", "max_overlap", "A", "W",
                  "W_minus_optimum", "kkt_residual", "complementarity", "active_pairs",
                  "force_imbalance")


def metrics_recorder(scene, comm, path, every, resume_after=None):
    """Every ``every`` iterations and at the end: one metrics pass (``measures.measure``, about
    the cost of an iteration; collective) and a row of ``METRIC_COLUMNS`` appended to the CSV
    file ``path`` by rank 0. The error measures: relative change (4.3), max overlap relative
    to d_kl, the paper's mean overlap proportion A (Definition 4.1), W and W minus
    output.w_optimum when the scene gives one, the KKT residual, complementarity
    max lambda |phi|, active pairs, and the force imbalance (the KKT residual's net forces
    relative to the contact forces, ``measures.measure``). With ``resume_after`` (a restart
    from that iteration) the file keeps its rows up to that iteration and continues. Returns a
    Hook."""
    from mpipack.stop import measures
    optimum = scene.output.w_optimum
    state = {"last": None}

    def rank0_writes(write):
        """Rank 0 writes; every rank learns whether it could (one broadcast), so that a full
        disk stops every rank (the hook's ``failed``), not rank 0 alone."""
        err = None
        if comm.rank == 0:
            try:
                write()
            except OSError as e:
                err = f"{path}: not written: {e.strerror or e}"
        return comm.bcast_object(err)

    def start():
        kept = []
        if resume_after is not None and os.path.exists(path):
            with open(path) as f:
                kept = [line for line in f.readlines()[1:] if int(line.split(",", 1)[0]) <= resume_after]
        with open(path, "w") as f:
            f.write(",".join(METRIC_COLUMNS) + "\n")
            f.writelines(kept)

    def record(ctx):
        if hook.failed is not None:
            return STOP
        if state["last"] == ctx.iteration:  # the end, right after a scheduled row
            return None
        state["last"] = ctx.iteration
        m, _ = measures.measure(ctx.solver)
        row = (ctx.iteration, ctx.elapsed, ctx.figures.get("relative_change", float("nan")),
               m["max_overlap"], m["overlap_A"], m["W"],
               m["W"] - optimum if optimum is not None else float("nan"),
               m["kkt_residual"], m["complementarity"], m["active_pairs"], m["force_imbalance"])

        def append():
            with open(path, "a") as f:
                f.write(",".join(repr(v) if isinstance(v, float) else str(v) for v in row) + "\n")
        hook.failed = rank0_writes(append)
        return STOP if hook.failed is not None else None

    hook = Hook(record, every=every, at_end=True, name="metrics")
    hook.failed = rank0_writes(start)  # the run stops at its first iteration when this failed
    if hook.failed is not None:
        hook.every = 1
    return hook
