"""Stop requests from signals: SIGTERM, SIGUSR1 (Slurm's --signal) and SIGINT ask every rank
to checkpoint and stop at the end of the current iteration. The request is a flag that every
iteration's reduction carries (``Solver.loop_reduction``), and the multiplier fit's too (a
fit can take thousands of steps), so all ranks see it together."""

import os
import signal
import sys

# set by a signal handler (``request_stop``), read into every reduction
_STOP_REQUEST = [0]


class Interrupted(Exception):
    """A collective computation (the multiplier fit of a certificate check) saw a stop request
    on some rank and ended early on every rank."""


def request_stop(signum=1):
    """Ask the loop to stop (and the caller to checkpoint) at the end of the current iteration
    on every rank. Safe in a signal handler."""
    _STOP_REQUEST[0] = max(1, int(signum))


def stop_requested():
    """The signal number of a pending stop request, or 0."""
    return _STOP_REQUEST[0]


def clear_stop_request():
    """Forget a stop request (a new run in the same process starts without one)."""
    _STOP_REQUEST[0] = 0


def install_handlers():
    """SIGTERM, SIGUSR1 and SIGINT request a stop (``request_stop``); a second SIGINT stops at
    once (exit 130, one line). Returns the handlers they replace (``restore_handlers``)."""

    def handler(signum, frame):
        if signum == signal.SIGINT and stop_requested():
            print("mpipack: interrupted again: stopping now, without a checkpoint", file=sys.stderr, flush=True)
            os._exit(130)
        request_stop(signum)

    return {sig: signal.signal(sig, handler) for sig in (signal.SIGTERM, signal.SIGUSR1, signal.SIGINT)}


def restore_handlers(previous):
    """Put back the handlers ``install_handlers`` replaced (a library call leaves the process as
    it found it)."""
    for sig, handler in previous.items():
        if handler is not None:
            signal.signal(sig, handler)
