"""Per-phase wall-clock timers of the loop, cheap enough to stay on in every run.

The loop and the solver call ``lap(PHASE)`` at the end of each phase: the time since the previous
lap is charged to that phase. Every instant between ``start`` and the last lap is charged to
exactly one phase, so the phases add up to the loop's wall time by construction (what is not
inside a named phase, such as the loop's own bookkeeping, lands in the phase that ends next).
One ``time.perf_counter`` call and one float addition per lap.

``report`` reduces the per-rank seconds (max and mean over ranks) on every rank.
"""

import time

import numpy as np

PHASES = ("step", "reduce", "forward", "exchange", "balance", "borders", "rows", "hooks")
STEP, REDUCE, FORWARD, EXCHANGE, BALANCE, BORDERS, ROWS, HOOKS = range(len(PHASES))

DESCRIPTIONS = {
    "step": "step kernel: lambda^n and X^{n+1} over the pair rows",
    "reduce": "the fused allreduce and reading its fields",
    "forward": "ghost positions from their owners (and the rebuild test)",
    "exchange": "rebuild: migrate particles with their pair history",
    "balance": "rebuild: recursive coordinate bisection",
    "borders": "rebuild: ghosts and far pair partners",
    "rows": "rebuild: cell sort and Verlet pair rows",
    "hooks": "hooks (progress, output, metrics) and the loop itself",
}


def process_age_seconds():
    """Seconds since this process started (Linux /proc), or NaN where that is not available:
    for the time to the first iteration, which includes the interpreter and the imports."""
    import os
    try:
        with open("/proc/self/stat") as f:
            start_ticks = float(f.read().rsplit(")", 1)[1].split()[19])
        with open("/proc/uptime") as f:
            uptime = float(f.read().split()[0])
        return uptime - start_ticks / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return float("nan")


class PhaseTimers:
    """Seconds per phase of the loop: ``lap(PHASE)`` adds the time since the last lap to PHASE
    (the phases are also attributes, ``timers.STEP``, for code that only holds the timers)."""
    STEP, REDUCE, FORWARD, EXCHANGE, BALANCE, BORDERS, ROWS, HOOKS = range(len(PHASES))

    def __init__(self):
        self.seconds = np.zeros(len(PHASES))
        self._last = None

    def start(self):
        """Zero the counters and start the clock."""
        self.seconds[:] = 0.0
        self._last = time.perf_counter()

    def stop(self):
        """Stop charging laps (a lap after stop is ignored)."""
        self._last = None

    def lap(self, phase):
        if self._last is None:
            return
        now = time.perf_counter()
        self.seconds[phase] += now - self._last
        self._last = now

    def report(self, comm, loop_seconds):
        """Phase table reduced over ranks: {phase: {"max", "mean", "share"}} plus totals.

        share = mean seconds / loop seconds; "covered" = sum of the mean shares (the phases
        cover the loop when it is close to 1). Collective.
        """
        mx = comm.allreduce(self.seconds.copy(), op="max")
        mean = comm.allreduce(self.seconds.copy(), op="sum") / comm.size
        out = {"loop_seconds": loop_seconds, "phases": {}}
        for k, name in enumerate(PHASES):
            out["phases"][name] = {"max": float(mx[k]), "mean": float(mean[k]),
                                   "share": float(mean[k] / loop_seconds) if loop_seconds > 0 else 0.0}
        out["covered"] = float(mean.sum() / loop_seconds) if loop_seconds > 0 else 0.0
        return out


def format_report(rep):
    """The phase table as text lines."""
    lines = [f"{'phase':<10} {'max s':>9} {'mean s':>9} {'share':>7}  what",
             ]
    for name in PHASES:
        p = rep["phases"][name]
        lines.append(f"{name:<10} {p['max']:>9.3f} {p['mean']:>9.3f} {100 * p['share']:>6.1f}%  "
                     f"{DESCRIPTIONS[name]}")
    lines.append(f"{'total':<10} {'':>9} {sum(p['mean'] for p in rep['phases'].values()):>9.3f} "
                 f"{100 * rep['covered']:>6.1f}%  of the loop's {rep['loop_seconds']:.3f} s "
                 f"(max and mean over ranks)")
    return lines
