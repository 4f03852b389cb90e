"""Stop requests from signals: SIGTERM, SIGUSR1 (Slurm's --signal) and SIGINT ask every rank
to checkpoint and stop at the end of the current iteration. The request is a flag that every
iteration's reduction carries (``Solver.loop_reduction``), so all ranks see it together."""

import os
import signal
import sys

# set by a signal handler (``request_stop``), read into every reduction
_STOP_REQUEST = [0]


def request_stop(signum=1):
    """Ask the loop to stop (and the caller to checkpoint) at the end of the current iteration
    on every rank. Safe in a signal handler."""
    _STOP_REQUEST[0] = max(1, int(signum))


def stop_requested():
    """The signal number of a pending stop request, or 0."""
    return _STOP_REQUEST[0]


def install_handlers():
    """SIGTERM, SIGUSR1 and SIGINT request a stop (``request_stop``); a second SIGINT stops at
    once (exit 130, one line)."""

    def handler(signum, frame):
        if signum == signal.SIGINT and stop_requested():
            print("mpipack: interrupted again: stopping now, without a checkpoint", file=sys.stderr, flush=True)
            os._exit(130)
        request_stop(signum)

    for sig in (signal.SIGTERM, signal.SIGUSR1, signal.SIGINT):
        signal.signal(sig, handler)
