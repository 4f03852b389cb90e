"""Exit codes and the errors behind them: one table for every command (``mpipack run``,
``check``, ``suite``, ...) and for the library API. The code is the same on every rank.

    0  converged (certified), or under the paper's rule (stop.rule = "eps") (4.3) fired on a
       feasible configuration or the requested iterations ran (stop.eps = 0), or under
       stop.rule = "jammed" the run stopped jammed (not certified); ``check``: stable
    1  internal error (a bug: please report it with the traceback); ``suite``: a case failed
    2  bad input (scene, option, checkpoint, memory): one line naming the problem
    3  numerical trouble: NaN, Inf, divergence or oscillation without progress (``watchdog``);
       the last good state is checkpointed; ``check``: the scene's parameters are unstable
    4  not converged within stop.max_iter or stop.max_seconds (the state is checkpointed)
    5  stopped with a checkpoint: SIGTERM, SIGUSR1, SIGINT or --walltime; continue with
       ``mpipack run --restart RUN_DIR``
"""

EXIT_OK, EXIT_INTERNAL, EXIT_INPUT, EXIT_NUMERICAL, EXIT_NOT_CONVERGED, EXIT_CHECKPOINTED = 0, 1, 2, 3, 4, 5
EXIT_UNSTABLE = EXIT_NUMERICAL  # ``mpipack check``: the parameters are outside the stable range
EXIT_FAILED = EXIT_INTERNAL     # ``mpipack suite``: a case did not end as expected
EXIT_MEANING = {0: "converged", 1: "internal error", 2: "bad input", 3: "numerical trouble",
                4: "not converged", 5: "stopped with a checkpoint"}


class InputError(Exception):
    """Bad input found while setting a run up: one line (exit 2)."""


class TooDenseError(RuntimeError):
    """The pair rows of the current configuration would not fit in memory (exit 2)."""


class NumericalError(RuntimeError):
    """NaN, Inf, divergence or oscillation without progress (``stop.watchdog``), exit 3.
    ``solver`` holds the last good state: positions of the last finite iteration and their
    multipliers. ``kind``: "non-finite", "diverged" or "stalled"."""

    def __init__(self, message, solver, kind="diverged"):
        super().__init__(message)
        self.solver, self.kind = solver, kind
