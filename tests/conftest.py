"""Shared helpers: run mpipack (or a test script) under ``mpirun`` with a self-contained env.

The tests do not rely on the caller having sourced tools/env.sh: the environment for every
subprocess is `mpipack.parallel.launcher.mpi_env`: os.environ plus what Open MPI needs to run as root and with
more ranks than cores. Every subprocess has a timeout, so a hang fails instead of blocking.
"""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
TESTS = Path(__file__).resolve().parent
MPI_SCRIPTS = TESTS / "mpi_scripts"

# arrays of an ``mpipack run --dump`` file
DUMP_KEYS = ("gid", "x", "x_prev", "diam", "pairs_gid", "pairs_lambda")

# generous: a healthy run of any test command takes a few seconds
TIMEOUT = 300


# the environment of every subprocess: the one `mpipack suite` builds for its runs (root,
# oversubscription, yield when idle, this checkout first on PYTHONPATH)
from mpipack.parallel.launcher import mpi_env


def mpirun(n, args, cwd, timeout=TIMEOUT):
    """``mpirun -n n <args>`` with output captured; returns CompletedProcess (never raises on
    a non-zero exit; raises subprocess.TimeoutExpired on a hang)."""
    cmd = ["mpirun", "--oversubscribe", "-n", str(n)] + [str(a) for a in args]
    return subprocess.run(cmd, cwd=str(cwd), env=mpi_env(), capture_output=True, text=True,
                          timeout=timeout)


def describe(proc):
    """A failure message with the command, exit code and captured output."""
    cmd = proc.args if isinstance(proc.args, str) else " ".join(map(str, proc.args))
    return (f"\n$ {cmd}\nexit code {proc.returncode}\n--- stdout ---\n{proc.stdout}"
            f"\n--- stderr ---\n{proc.stderr}")


def mpipack_run(n_ranks, workdir, scene=None, sets=(), dump=False, extra=(), timeout=TIMEOUT,
                quiet=True):
    """Run ``mpipack run`` on n_ranks ranks in workdir (output folder workdir/out).

    Returns (proc, summary dict or None, dump dict or None).
    """
    workdir = Path(workdir)
    out = workdir / "out"
    args = [sys.executable, "-m", "mpipack.cli", "run"]
    if scene is not None:
        args.append(scene)
    for s in sets:
        args += ["--set", s]
    args += ["--out", out]
    if quiet:
        args.append("--quiet")
    dump_path = workdir / "final.npz"
    if dump:
        args += ["--dump", dump_path]
    args += list(extra)
    proc = mpirun(n_ranks, args, cwd=workdir, timeout=timeout)
    summary = None
    if (out / "summary.json").exists():
        summary = json.loads((out / "summary.json").read_text())
    data = None
    if dump and dump_path.exists():
        with np.load(dump_path) as z:
            data = {k: z[k] for k in z.files}
    return proc, summary, data


@pytest.fixture
def run_mpipack(tmp_path):
    """run_mpipack(n_ranks, scene=None, sets=(), dump=False, extra=(), tag=None, timeout=...,
    quiet=True): mpipack_run in a fresh sub-folder of tmp_path."""
    counter = {"k": 0}

    def _run(n_ranks, scene=None, sets=(), dump=False, extra=(), tag=None, timeout=TIMEOUT,
             quiet=True):
        counter["k"] += 1
        d = tmp_path / (tag or f"run{counter['k']}-np{n_ranks}")
        d.mkdir(parents=True, exist_ok=True)
        return mpipack_run(n_ranks, d, scene=scene, sets=sets, dump=dump, extra=extra,
                           timeout=timeout, quiet=quiet)

    return _run


def assert_bitwise_equal(ref, other, what):
    assert set(ref) == set(DUMP_KEYS) and set(other) == set(DUMP_KEYS), (sorted(ref), sorted(other))
    for k in DUMP_KEYS:
        a, b = ref[k], other[k]
        assert a.dtype == b.dtype and a.shape == b.shape, (what, k, a.dtype, b.dtype, a.shape, b.shape)
        if not np.array_equal(a, b):
            bad = np.argwhere(a != b) if a.shape == b.shape else None
            pytest.fail(f"{what}: '{k}' differs bitwise at {len(bad)} entries, first {bad[:3].tolist()}; "
                        f"max |diff| {np.max(np.abs(a.astype(float) - b.astype(float)))}")


def step_each(s, n, fn):
    """Advance Solver ``s`` by n iterations through the one loop (engine.loop.run, stop rule: n more
    iterations), calling fn(figures) after each. Returns run's result dict.

    Tests observe the trajectory through a hook, as any other user of the loop does."""
    from mpipack.engine import hooks, loop
    scene = s.scene.replace(stop={"eps": 0.0, "max_iter": s.state.iteration + n})
    _, res = loop.run(scene, s.comm, hooks=[hooks.Hook(lambda ctx: fn(ctx.figures), every=1)],
                            solver=s)
    return res
