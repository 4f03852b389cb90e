"""The per-rank state: local and ghost particle arrays plus the pair store. No MPI.

Shapes (n_total = n_local + n_ghost, b = dim):

    x        (n_total, b)  X^n: rows [0, n_local) local particles, then ghosts
    x_prev   (n_total, b)  X^{n-1} (local rows meaningful; X^{-1} = X^0, zero initial velocity)
    x_new    (n_total, b)  scratch for X^{n+1}; the three rotate, so ghosts rows exist in all
    gid      (n_total,)    global ids, int64
    diam     (n_total,)    diameters d_i
    x_build  (n_local, b)  local positions when the pair rows were last built
    pair_offsets (n_local+1,), pair_j int32 (n_pairs,), pair_lambda (n_pairs,):
                           the pair store, one row per local particle, partners in gid order
    pair_work              the fire-al pass's half list of the rows and its terms buffer
                           (``kernels.fire.pair_work``), made by the method when it needs it;
                           None after every build of the rows
    pair_mirror int64 (n_pairs,)  each entry's mirror as the build found it (the entry of the
                           partner's row with this particle, or -1), until the half list is
                           made from it; None where the build did not find them

    x_lin    (n_total, b)  NAP/NAV only: the outer iterate X^p the constraints are linearised
                           about (ghost rows too); None for DAHA/AHA
    qn       (n_local, 2m+1, b)  the L-BFGS inner solver's per-sphere memory (``qn``), local
                           rows only; None until the fire-al schedule switches to it
    walls    (n_walls, 8)  the container's walls (``kernels.walls``), the same on every rank;
                           (0, 8) without a container
    wall_lambda (n_local, n_walls)  each local sphere's wall multipliers lambda_iw, which
                           travel with the sphere (local rows only)

``lambda_fresh`` is True when pair_lambda already holds lambda for the current X (at the start,
lambda^0; after ``finish``), False when it holds lambda^{n-1} and the next step must first
update it from X^n.

The whole state is serialisable by gid without the partition: positions, previous positions,
diameters and, per particle, its (partner gid, lambda > 0) history. ``BlockState`` is that
form: what a checkpoint holds and what ``Solver.initialise`` can start from.
"""

from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from mpipack.jit import njit


@dataclass
class BlockState:
    """The state of one rank's block of consecutive global ids, independent of the partition.

    Rank r of P holds gids [gid_lo, gid_lo + m) (by ``comm.to_gid_blocks``: N r/P .. N (r+1)/P),
    rows in gid order:

        x, x_prev      (m, b)   X^n and X^{n-1}
        x_lin          (m, b)   NAP/NAV's linearisation point X^p, else None
        qn             (m, 2k+1, b)  the L-BFGS memory (k pairs) (``State.qn``), else None
        wall_lambda    (m, n_walls)  the wall multipliers (``State.wall_lambda``), else None
        diam           (m,)
        hist_count     (m,)     int64, partners with lambda > 0 of each particle
        hist_gid       (k,)     int64, their gids (each particle's run in gid order)
        hist_lambda    (k,)     their multipliers (each pair appears under both particles)

    and the scalars that are the same on every rank: n_global, dim, iteration, lambda_fresh
    (see ``State``), counters (dict of ints/floats), extra (dict: whatever else a continuation
    needs, e.g. an adaptive controller's state).
    """
    n_global: int
    dim: int
    gid_lo: int
    x: np.ndarray
    x_prev: np.ndarray
    diam: np.ndarray
    hist_count: np.ndarray
    hist_gid: np.ndarray
    hist_lambda: np.ndarray
    x_lin: Optional[np.ndarray] = None
    qn: Optional[np.ndarray] = None
    wall_lambda: Optional[np.ndarray] = None
    iteration: int = 0
    lambda_fresh: bool = True
    counters: dict = field(default_factory=dict)
    extra: dict = field(default_factory=dict)

    @property
    def gids(self):
        return np.arange(self.gid_lo, self.gid_lo + self.x.shape[0], dtype=np.int64)

    def hist_offsets(self):
        off = np.zeros(self.hist_count.shape[0] + 1, dtype=np.int64)
        np.cumsum(self.hist_count, out=off[1:])
        return off


class State:
    def __init__(self, dim, n_global):
        self.dim = dim
        self.n_global = n_global
        self.n_local = 0
        self.n_ghost = 0
        self.x = np.zeros((0, dim))
        self.x_prev = np.zeros((0, dim))
        self.x_new = np.zeros((0, dim))
        self.gid = np.zeros(0, dtype=np.int64)
        self.diam = np.zeros(0)
        self.x_build = np.zeros((0, dim))
        self.pair_offsets = np.zeros(1, dtype=np.int64)
        self.pair_j = np.zeros(0, dtype=np.int32)
        self.pair_lambda = np.zeros(0)
        self.pair_work = None
        self.pair_mirror = None
        self.x_lin = None  # linearisation point X^p of the nested methods (n_total, b)
        self.qn = None  # the L-BFGS memory (n_local, 2m+1, b), once the schedule uses it
        self.walls = np.zeros((0, 8))  # the container's walls (``kernels.walls``)
        self.wall_lambda = np.zeros((0, 0))  # (n_local, n_walls)
        self.lambda_fresh = True
        self.iteration = 0

    @property
    def n_total(self):
        return self.n_local + self.n_ghost

    def set_particles(self, local, ghost):
        """Replace local and ghost particles by fresh copies.

        local: dict with x, x_prev (n_local, b), gid, diam (n_local,) and, for the nested
        methods, x_lin (n_local, b); ghost: dict with x (n_ghost, b), gid, diam and x_lin if
        local has it.
        """
        n_local, n_ghost = local["x"].shape[0], ghost["x"].shape[0]
        n = n_local + n_ghost
        self.n_local, self.n_ghost = n_local, n_ghost
        self.x = np.concatenate([local["x"], ghost["x"]]).reshape(n, self.dim)
        self.x_prev = np.concatenate([local["x_prev"], ghost["x"]]).reshape(n, self.dim)
        self.x_new = np.empty((n, self.dim))
        self.gid = np.concatenate([local["gid"], ghost["gid"]]).astype(np.int64)
        self.diam = np.concatenate([local["diam"], ghost["diam"]]).astype(np.float64)
        if "x_lin" in local:
            self.x_lin = np.concatenate([local["x_lin"], ghost["x_lin"]]).reshape(n, self.dim)
        if "qn" in local:
            self.qn = np.ascontiguousarray(local["qn"])
        if "wall_lambda" in local:
            self.wall_lambda = np.ascontiguousarray(local["wall_lambda"]).reshape(n_local, self.walls.shape[0])
        else:
            self.wall_lambda = np.zeros((n_local, self.walls.shape[0]))

    def local_fields(self):
        """Copies of the per-particle arrays that travel with a local particle."""
        n = self.n_local
        out = {"x": self.x[:n].copy(), "x_prev": self.x_prev[:n].copy(),
               "gid": self.gid[:n].copy(), "diam": self.diam[:n].copy()}
        if self.x_lin is not None:
            out["x_lin"] = self.x_lin[:n].copy()
        if self.qn is not None:
            out["qn"] = self.qn[:n].copy()
        if self.walls.shape[0] > 0:
            out["wall_lambda"] = self.wall_lambda[:n].copy()
        return out

    def rotate(self):
        """After a step: (x_prev, x, x_new) <- (x, x_new, x_prev)."""
        self.x_prev, self.x, self.x_new = self.x, self.x_new, self.x_prev

    def local_pairs(self):
        """(gid_i, gid_j, lambda) of every row entry with lambda > 0 (each pair from both ends)."""
        counts = np.diff(self.pair_offsets)
        gi = np.repeat(self.gid[: self.n_local], counts)
        gj = self.gid[self.pair_j]
        keep = self.pair_lambda > 0
        return gi[keep], gj[keep], self.pair_lambda[keep]


@njit(cache=True)
def gather_rows(offsets, rows):
    """Ragged gather: entries of rows[k] (rows of a CSR with ``offsets``), in that order.

    Returns (new_offsets (len(rows)+1,), entry_index) such that entry_index[new_offsets[k]:
    new_offsets[k+1]] are the flat positions of row rows[k].
    """
    m = rows.shape[0]
    new_offsets = np.zeros(m + 1, dtype=np.int64)
    for k in range(m):
        r = rows[k]
        new_offsets[k + 1] = new_offsets[k] + offsets[r + 1] - offsets[r]
    idx = np.empty(new_offsets[m], dtype=np.int64)
    for k in range(m):
        r = rows[k]
        p = new_offsets[k]
        for e in range(offsets[r], offsets[r + 1]):
            idx[p] = e
            p += 1
    return new_offsets, idx
