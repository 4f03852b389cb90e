"""What a run leaves in its output folder, as hooks on the loop: snapshots (parallel HDF5 +
XDMF, ``io.snapshots``), checkpoints (``io.checkpoint``), and the state a checkpoint holds.
The file formats live in ``mpipack.io``; this module decides what goes in them. h5py is
imported only when a snapshot or checkpoint is actually written.

Run folder (``--out``, default mpipack-out/<scene name>):

    summary.json     what ran, how it ended (every exit), the certificate, figures, timings
    metrics.csv      error measures every output.metrics_every iterations (when asked)
    snapshots.h5     the start (iteration 0), every output.snapshot_every iterations and the
                     end, with the contact pairs (io/snapshots.py)
    snapshots.xmf    the same series for ParaView (File > Open, or pvpython OpenDataFile);
                     snapshots_contacts.xmf: its contact network (the force chains)
    view.py          a ParaView script showing them: pvbatch view.py --png view.png (headless:
                     under xvfb-run, io/paraview.py)
    container.vtu    the container's surface (a run with a container; io/container_mesh.py)
    checkpoint.h5    the last checkpoint: everything to continue bit for bit (--restart)
    vtk/             after ``mpipack vtk RUN_DIR``: one .vtu per snapshot and snapshots.pvd
"""

import json
import os
import time

import numpy as np

from mpipack import __version__
from mpipack.stop import measures
from mpipack.engine.hooks import STOP, Hook


def _write_errors():
    """The errors of a file that could not be written (a full disk, a vanished folder): the
    writers agree on them on every rank before any rank leaves a collective call."""
    from mpipack.io.checkpoint import CheckpointError
    from mpipack.io.snapshots import SnapshotError
    return (SnapshotError, CheckpointError, OSError)

SNAPSHOT_FILE = "snapshots.h5"
CHECKPOINT_FILE = "checkpoint.h5"


def file_attrs(scene, comm):
    """Attributes that make a file describe its own run."""
    return {"scene": scene.as_dict(), "parameters": scene.as_dict()["method"], "ranks": comm.size,
            "version": __version__}


def snapshot_fields(solver):
    """Per-sphere fields of a snapshot, local rows (collective: a metrics pass for the
    pressure mu_i = sum_j lambda_ij, the active contacts and the net force |g_i|, the sphere's
    row of the KKT residual), and the contact pairs: (gid_i, gid_j, lambda_ij) with
    lambda_ij > 0 and gid_i < gid_j (each pair once over all ranks), lambda_ij the multiplier
    the pressure sums. Returns (gid, fields, figures, pairs)."""
    st = solver.state
    n = st.n_local
    entries = int(st.pair_offsets[n])
    pair_force = np.zeros(entries)
    fig, spheres = measures.measure(solver, overlap_a=False, pair_force=pair_force)
    # the entries with a force first (a dense start's rows hold hundreds of entries a sphere,
    # few or none of them with a force), then their spheres' gids
    e = np.flatnonzero(pair_force > 0)
    gi = st.gid[np.searchsorted(st.pair_offsets[:n + 1], e, side="right") - 1]
    gj = st.gid[st.pair_j[e]]
    keep = gi < gj
    pairs = (gi[keep].astype(np.int64), gj[keep].astype(np.int64), pair_force[e[keep]])
    return st.gid[:n], {"position": st.x[:n], "diameter": st.diam[:n], **spheres}, fig, pairs


class Snapshots:
    """Snapshots of the start (iteration 0; not again on a restart, whose file keeps it), every
    ``every`` iterations (0: none on a schedule) and of the end, each with its contact pairs."""

    def __init__(self, scene, comm, out_dir, every, truncate_after=None):
        self.scene, self.comm, self.every = scene, comm, every
        self.path = os.path.join(out_dir, SNAPSHOT_FILE)
        self.truncate_after = truncate_after
        self.writer = None
        self.last_iteration = None
        self.seconds = 0.0
        self.failed = None  # the one-line message of a snapshot that could not be written
        self._scheduled = None
        self.container_path = None  # container.vtu once written

    def hooks(self):
        self._scheduled = Hook(self._due, every=self.every if self.every > 0 else None, at_end=True,
                               name="snapshot")
        if self.truncate_after is not None:  # a restart: the file holds the start already
            return [self._scheduled]
        return [Hook(self._start, at_start=True, name="snapshot-start"), self._scheduled]

    def _start(self, ctx):
        """The initial state, iteration 0. The loop ignores what an at_start hook answers: a
        failure stops the run after its first iteration (``_due``)."""
        if not self.safe_write(ctx.solver, ctx.iteration, ctx.elapsed, ctx.figures):
            self._scheduled.every = 1

    def _due(self, ctx):
        """A snapshot on schedule; one that cannot be written stops the run (collectively)."""
        if self.failed is not None and ctx.result is None:  # the start's failure
            return STOP
        return None if self.safe_write(ctx.solver, ctx.iteration, ctx.elapsed, ctx.figures) else STOP

    def safe_write(self, solver, iteration, elapsed, figures):
        """``write``, a failure kept in ``failed`` instead of raised; True when written."""
        try:
            self.write(solver, iteration, elapsed, figures)
            return True
        except _write_errors() as e:
            self.failed = str(e).splitlines()[0] if str(e) else repr(e)
            return False

    def write(self, solver, iteration, elapsed, figures):
        if self.last_iteration == iteration:
            return
        from mpipack.io.snapshots import SnapshotWriter
        t0 = time.perf_counter()
        if self.writer is None:
            self.writer = SnapshotWriter(self.comm, self.path, self.scene.n, self.scene.dim,
                                         file_attrs(self.scene, self.comm),
                                         truncate_after=self.truncate_after)
            self._write_container()
        gid, fields, fig, pairs = snapshot_fields(solver)
        self.writer.write(gid, fields, {
            "iteration": iteration, "wall_seconds": elapsed,
            "relative_change": figures.get("relative_change", float("nan")),
            "max_overlap": fig["max_overlap"], "W": fig["W"], "kkt_residual": fig["kkt_residual"]},
            pairs=pairs)
        self.last_iteration = iteration
        self.seconds += time.perf_counter() - t0

    def _write_container(self):
        """The container's surface beside the snapshots (rank 0, once per writer; collective:
        a failure is a SnapshotError on every rank)."""
        if not self.scene.container.active:
            return
        from mpipack.io import container_mesh
        from mpipack.io.snapshots import SnapshotError
        folder = os.path.dirname(self.path)
        err = None
        if self.comm.rank == 0:
            try:
                container_mesh.write(folder, self.scene.as_dict()["container"], self.scene.dim)
            except OSError as e:
                err = f"{container_mesh.container_path(folder)}: not written: {e.strerror or e}"
        err = self.comm.bcast_object(err)
        if err is not None:
            raise SnapshotError(err)
        self.container_path = container_mesh.container_path(folder)

    def close(self):
        if self.writer is not None:
            self.writer.close()


class Checkpoints:
    """Checkpoints every ``every`` iterations (0: none on a schedule), and on request (signal,
    wall-time limit, numerical trouble). Each write replaces checkpoint.h5 atomically."""

    def __init__(self, scene, comm, out_dir, every):
        self.scene, self.comm, self.every = scene, comm, every
        self.path = os.path.join(out_dir, CHECKPOINT_FILE)
        self.last_iteration = None
        self.last_seconds = None  # wall seconds of the last write (for the wall-time margin)
        self.failed = None  # the one-line message of a checkpoint that could not be written

    def hooks(self):
        out = [Hook(self._at_stop, at_stop=True, name="checkpoint-at-stop")]
        if self.every > 0:
            out.append(Hook(lambda ctx: None if self.safe_write(ctx.solver) else STOP, every=self.every,
                            name="checkpoint"))
        return out

    def safe_write(self, solver):
        """``write``, a failure kept in ``failed`` (the previous checkpoint stays whole) instead
        of raised; True when written."""
        try:
            self.write(solver)
            return True
        except _write_errors() as e:
            self.failed = str(e).splitlines()[0] if str(e) else repr(e)
            return False

    def keeps(self, reason):
        """A stop whose state a later run continues: a signal or the wall time (exit 5), a bound
        reached first (exit 4); not the requested iterations of stop.eps = 0 (exit 0)."""
        stop = self.scene.stop
        if reason in ("signal", "walltime"):
            return True
        return reason in ("max_iter", "max_seconds") and not (stop.rule == "eps" and stop.eps == 0)

    def _at_stop(self, ctx):
        """The checkpoint of a stop, written before anything else: the state exactly as the loop
        left it (the final figures update the multipliers), and within a scheduler's grace
        period (nothing costly comes first)."""
        if self.keeps(ctx.stop_reason):
            self.safe_write(ctx.solver)

    def write(self, solver):
        """Collective. Returns the seconds the write took."""
        from mpipack.io.checkpoint import write_checkpoint
        if self.last_iteration == solver.state.iteration:
            return 0.0
        b = solver.export_state()
        block = {"gid_lo": b.gid_lo, "x": b.x, "x_prev": b.x_prev, "diam": b.diam,
                 "hist_count": b.hist_count, "hist_gid": b.hist_gid, "hist_lambda": b.hist_lambda}
        if b.x_lin is not None:
            block["x_lin"] = b.x_lin
        if b.qn is not None:
            block["qn"] = b.qn
        if b.wall_lambda is not None:
            block["wall_lambda"] = b.wall_lambda
        scalars = {"iteration": b.iteration, "lambda_fresh": b.lambda_fresh,
                   "counters": b.counters, "extra": b.extra}
        seconds = write_checkpoint(self.comm, self.path, self.scene.n, self.scene.dim, block,
                                   scalars, file_attrs(self.scene, self.comm))
        self.last_iteration = solver.state.iteration
        self.last_seconds = seconds
        return seconds


class NoCheckpoints:
    """The checkpoints of a run that writes no file (``mpipack.run`` without ``out``)."""
    path = None
    last_iteration = None
    last_seconds = None
    failed = None

    def hooks(self):
        return []

    def write(self, solver):
        return 0.0

    def safe_write(self, solver):
        return True


def state_problem(block, scalars, n):
    """What makes a checkpoint's state impossible (this rank's block), or None: positions that
    are not finite, diameters that are not positive, partner gids outside [0, N) or a sphere its
    own partner, multipliers that are negative or not finite, scalars missing or of the wrong
    kind. A run from such a state would fail far from its cause, or silently compute nonsense."""
    for k in ("x", "x_prev", "x_lin", "qn", "wall_lambda"):
        if block.get(k) is not None and not np.all(np.isfinite(block[k])):
            return f"particles/{k} holds values that are not finite"
    if block.get("wall_lambda") is not None and block["wall_lambda"].size and block["wall_lambda"].min() < 0:
        return "particles/wall_lambda holds negative multipliers"
    d = block["diam"]
    if not np.all(np.isfinite(d)) or np.any(d <= 0):
        return "particles/diam holds diameters that are not positive"
    gid, lam, count = block["hist_gid"], block["hist_lambda"], block["hist_count"]
    if gid.size and (gid.min() < 0 or gid.max() >= n):
        return f"history/gid holds partners outside [0, {n})"
    owner = block["gid_lo"] + np.repeat(np.arange(count.size), count)
    if np.any(gid == owner):
        return "history/gid holds a sphere as its own partner"
    if lam.size and (not np.all(np.isfinite(lam)) or lam.min() < 0):
        return "history/lambda holds multipliers that are negative or not finite"
    try:
        iteration = scalars["iteration"]
        ok = (isinstance(iteration, int) and iteration >= 0 and isinstance(scalars["lambda_fresh"], bool)
              and isinstance(scalars.get("counters", {}), dict) and isinstance(scalars.get("extra", {}), dict))
    except (KeyError, TypeError):
        ok = False
    if not ok:
        return "its scalars (iteration, lambda_fresh, counters) are missing or of the wrong kind"
    return None


def read_state(comm, path):
    """(BlockState of this rank, scene table, file attributes) from a checkpoint file or a run
    folder holding checkpoint.h5. Raises io.checkpoint.CheckpointError (one line)."""
    from mpipack.io.checkpoint import CheckpointError, read_checkpoint
    from mpipack.parallel.state import BlockState
    if os.path.isdir(path):
        path = os.path.join(path, CHECKPOINT_FILE)
    block, scalars, attrs = read_checkpoint(comm, path)
    scene = attrs.get("scene")
    if isinstance(scene, str):
        try:
            scene = json.loads(scene)
        except ValueError:
            scene = None
    if not isinstance(scene, dict):
        raise CheckpointError(f"checkpoint {path}: no scene recorded in it")
    problem = state_problem(block, scalars, int(attrs["n"]))
    if problem:
        raise CheckpointError(f"{path}: damaged checkpoint: {problem}")
    state = BlockState(
        n_global=int(attrs["n"]), dim=int(attrs["dim"]), gid_lo=int(block["gid_lo"]),
        x=block["x"], x_prev=block["x_prev"], diam=block["diam"],
        hist_count=block["hist_count"], hist_gid=block["hist_gid"],
        hist_lambda=block["hist_lambda"], x_lin=block.get("x_lin"), qn=block.get("qn"),
        wall_lambda=block.get("wall_lambda"), iteration=int(scalars["iteration"]), lambda_fresh=bool(scalars["lambda_fresh"]),
        counters=dict(scalars.get("counters", {})), extra=dict(scalars.get("extra", {})))
    return state, scene, attrs
