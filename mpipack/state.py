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

``lambda_fresh`` is True when pair_lambda already holds lambda for the current X (at the start,
lambda^0; after ``finish``), False when it holds lambda^{n-1} and the next step must first
update it from X^n.

The whole state is serialisable by gid without the partition: positions, previous positions,
diameters and, per particle, its (partner gid, lambda > 0) history.
"""

import numpy as np
from numba import njit


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
        self.lambda_fresh = True
        self.iteration = 0

    @property
    def n_total(self):
        return self.n_local + self.n_ghost

    def set_particles(self, x, x_prev, gid, diam, ghost_x, ghost_gid, ghost_diam):
        """Replace local and ghost particles (arrays are copied into fresh storage)."""
        n_local, n_ghost = x.shape[0], ghost_x.shape[0]
        n = n_local + n_ghost
        self.n_local, self.n_ghost = n_local, n_ghost
        self.x = np.empty((n, self.dim))
        self.x[:n_local] = x
        self.x[n_local:] = ghost_x
        self.x_prev = np.empty((n, self.dim))
        self.x_prev[:n_local] = x_prev
        self.x_prev[n_local:] = ghost_x
        self.x_new = np.empty((n, self.dim))
        self.gid = np.concatenate([gid, ghost_gid]).astype(np.int64)
        self.diam = np.concatenate([diam, ghost_diam]).astype(np.float64)

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
