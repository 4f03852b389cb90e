"""The library API: what the command line, the experiments and the tests share.

    scene = mpipack.load_scene("default", overrides=["n=500"], seed=1)
    result = mpipack.run(scene, out="my-run")     # on MPI.COMM_WORLD (serial in a plain python)
    result.converged, result.iterations, result.certificate["kkt"]["value"]
    snap = mpipack.read_snapshot("my-run")        # the last snapshot of a run folder

``run`` is ``mpipack run`` without its argument parsing: the same run, files, summary and exit
code. Importing this module imports neither numpy, numba nor mpi4py; each call imports what it
needs.
"""

import dataclasses
import os
from typing import Optional


@dataclasses.dataclass
class Result:
    """How a run ended (the same on every rank).

    exit_code       0 converged, 2 bad input, 3 numerical trouble, 4 not converged, 5 stopped
                    with a checkpoint (``mpipack.errors``)
    converged       the final packing meets every tolerance of its certificate
    iterations      the iteration count at the end
    stop_reason     what stopped the loop: "certified", "eps", "max_iter", "max_seconds",
                    "signal" or a hook's name (None when the run did not start or failed)
    certificate     {"overlap" | "kkt" | "settled": {"value", "tol", "ok", ...}}
    figures         the final figures: W, max_overlap, kkt_residual, density, ... (summary.json's)
    summary         everything summary.json holds
    files           the files the run wrote
    error           the one-line error of exit codes 2 and 3
    particles       with ``gather=True``, on rank 0: {"gid", "x", "diam", "pairs_gid",
                    "pairs_lambda", ...} in gid order; else None
    """
    exit_code: int
    converged: bool
    iterations: int
    stop_reason: Optional[str]
    certificate: dict
    figures: dict
    summary: dict
    files: list
    error: Optional[str] = None
    particles: Optional[dict] = None


def load_scene(scene=None, overrides=(), seed=None, **settings):
    """A validated, frozen ``config.Scene``: a built-in name (``mpipack scenes``), a TOML path
    or None (the default scene), with ``overrides`` as "key=value" strings (as ``--set``) and
    keyword settings where a double underscore stands for the dot (``stop__max_iter=100``).
    Raises ``config.SceneError`` (a one-line message) on bad input."""
    from mpipack import config
    return config.load(scene, tuple(overrides), seed, settings=_dotted(settings))


def run(scene=None, *, comm=None, out=None, seed=None, overrides=(), options=None, restart=None,
        overwrite=False, dump=None, quiet=True, profile=False, hooks=(), gather=False, **settings):
    """Run a scene to its stop rule, as ``mpipack run`` does; returns a ``Result``.

    scene: a ``Scene`` (``load_scene``), a built-in name, a TOML path, or None (the default);
    comm: an mpi4py communicator (default MPI.COMM_WORLD: serial in a plain python, parallel
    under mpirun; every rank calls ``run``); out: the run folder (None: no file is written, not
    even summary.json); overrides: "key=value" strings; options: {"stop.max_iter": 100}; keyword
    settings with a double underscore for the dot (``stop__max_iter=100``); restart: a run
    folder or checkpoint to continue (in place unless ``out``); overwrite: replace the run that
    ``out`` holds (else a folder holding another run is refused, exit 2); hooks: extra ``engine.hooks.Hook``s; gather: the final
    particles on rank 0 in ``Result.particles``.
    """
    from mpipack.engine import runner
    from mpipack.parallel.comm import Comm
    from mpipack.stop.signals import clear_stop_request
    clear_stop_request()  # a signal that stopped an earlier run of this process is spent
    values = {**(options or {}), **_dotted(settings)}
    request = runner.RunRequest(scene=scene, overrides=tuple(overrides), settings=values, seed=seed,
                                out=out, dump=dump, quiet=quiet, profile=profile, restart=restart,
                                overwrite=overwrite, silent=quiet,
                                files=out is not None or restart is not None, hooks=tuple(hooks))
    comm = Comm(comm)
    outcome = runner.run_request(comm, request)
    summary = outcome.summary or {}
    res = outcome.result or {}
    particles = outcome.solver.gather() if gather and outcome.solver is not None else None
    figures = {k: summary[k] for k in ("W", "max_overlap", "kkt_residual", "kkt_residual_run",
                                       "force_imbalance", "density", "density_radius", "relative_change",
                                       "complementarity", "overlap_A", "active_pairs", "wall_seconds",
                                       "loop_seconds", "particle_iterations_per_second") if k in summary}
    return Result(exit_code=outcome.code, converged=bool(res.get("converged", False)),
                  iterations=int(res.get("iterations", summary.get("iterations", 0)) or 0),
                  stop_reason=res.get("stop_reason"), certificate=res.get("certificate", {}),
                  figures=figures, summary=summary, files=list(summary.get("files", [])),
                  error=outcome.message, particles=particles)


@dataclasses.dataclass
class Snapshot:
    """One snapshot of a run, in gid order: position (N, b), diameter (N,), gid (N,), every
    per-sphere field (``fields``: position, diameter, pressure, contacts, net_force), its
    iteration and its attributes (W, max overlap, KKT residual, wall seconds, ...)."""
    iteration: int
    position: object
    diameter: object
    gid: object
    fields: dict
    attrs: dict


def read_snapshot(path, iteration=None):
    """The snapshot of ``iteration`` (None: the last) from a run folder or a snapshots.h5 file,
    read serially. Raises ``io.SnapshotError`` or FileNotFoundError (one line)."""
    import numpy as np
    from mpipack.io import SNAPSHOT_FILE
    from mpipack.io.snapshots import read_snapshot as read
    if os.path.isdir(path):
        path = os.path.join(path, SNAPSHOT_FILE)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"no snapshot file at {path}")
    fields, attrs = read(path, iteration)
    n = fields["position"].shape[0]
    gid = fields.get("gid", np.arange(n, dtype=np.int64))
    return Snapshot(iteration=int(attrs.get("iteration", -1)), position=fields["position"],
                    diameter=fields["diameter"], gid=gid, fields=fields, attrs=attrs)


def _dotted(settings):
    """{"stop__max_iter": 100} -> {"stop.max_iter": 100}."""
    return {k.replace("__", "."): v for k, v in settings.items()}
