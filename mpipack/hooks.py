"""Hooks: what the loop runs besides iterating, each on a schedule (after Dedalus' evaluator
handlers: ``iter=``, ``wall_dt=``).

A hook is a callable ``fn(ctx)`` with a schedule:

    every      run after every K-th iteration (iteration % K == 0)
    wall_dt    run when the loop's wall clock has passed the next multiple of T seconds
    at_start   run once after set-up, before the first iteration (ctx.figures is empty)
    at_end     run once after the loop, when the final figures are in ctx.result

The loop calls hooks on every rank at the same iterations: the wall clock it uses is the
maximum over ranks, which travels in the per-iteration reduction, so a wall-time schedule is a
collective decision too. A hook may do collective work (write a file, reduce a metric) and may
ask the loop to stop by returning ``STOP``; it must then decide from values that are the same
on every rank (reduced figures, the iteration count), or the ranks would part ways.

``ctx`` (a ``Context``) gives: solver, iteration, figures (the last iteration's reduced figures),
elapsed (loop wall seconds, the same on every rank), result (at_end only), and ``stop_reason``.
"""

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
    def __init__(self, fn, every=None, wall_dt=None, at_start=False, at_end=False, name=None):
        if every is not None and every < 1:
            raise ValueError("hook 'every' must be >= 1")
        self.fn = fn
        self.every = every
        self.wall_dt = wall_dt if wall_dt else None
        self.at_start = at_start
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
