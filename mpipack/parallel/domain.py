"""Spatial partition of particles across ranks: recursive coordinate bisection (RCB).

The partition is a binary tree of axis-aligned cuts. Each leaf is one rank's box (outer faces
at +-inf), so every point of space has exactly one owner and a point's owner is found by
walking the tree. Cuts are chosen collectively from allreduced counts so that each side holds
a share of the particles proportional to its number of ranks; the cut axis is the longest
extent of the node's particles. Works for a dense Gaussian cloud as well as for an expanding or
a lattice-like one, and with more ranks than particles (those ranks own empty boxes).

The partition never changes results (kernels sum pairs in gid order and reductions are exact),
only the load balance. No physics here.
"""

import numpy as np

from mpipack.jit import njit

# A cut is searched by multisection: each round counts, in ONE allreduce for every node of the
# level, the particles below _SECTIONS candidate cuts evenly spread over the node's bracket and
# keeps the section where the count reaches the target. _ROUNDS rounds narrow the bracket by
# 64^10 = 2^60, as 60 bisection steps did (one allreduce each): the bracket then ends at float
# resolution, the cut just above the target-th smallest coordinate.
_SECTIONS = 64
_ROUNDS = 10


class Partition:
    """RCB tree and the leaf boxes.

    axis, cut, left, right: per tree node (left/right < 0 encode leaf rank as -1 - rank);
    lo, hi: (P, b) box of each rank.
    """

    def __init__(self, axis, cut, left, right, lo, hi):
        self.axis = axis
        self.cut = cut
        self.left = left
        self.right = right
        self.lo = lo
        self.hi = hi

    @staticmethod
    def whole_space(b):
        """The one-rank partition."""
        return Partition(np.zeros(0, np.int64), np.zeros(0), np.zeros(0, np.int64),
                         np.zeros(0, np.int64), np.full((1, b), -np.inf), np.full((1, b), np.inf))

    def owners(self, x, n):
        """Owner rank of each of x[:n]."""
        if self.lo.shape[0] == 1:
            return np.zeros(n, dtype=np.int64)
        return _owners(x, n, self.axis, self.cut, self.left, self.right)


@njit(cache=True)
def _owners(x, n, axis, cut, left, right):
    out = np.empty(n, dtype=np.int64)
    for i in range(n):
        node = 0
        while True:
            nxt = left[node] if x[i, axis[node]] < cut[node] else right[node]
            if nxt < 0:
                out[i] = -1 - nxt
                break
            node = nxt
    return out


@njit(cache=True)
def _node_bbox(x, n, node_of, n_nodes):
    b = x.shape[1]
    lo = np.full((n_nodes, b), np.inf)
    hi = np.full((n_nodes, b), -np.inf)
    for i in range(n):
        m = node_of[i]
        if m < 0:
            continue
        for k in range(b):
            v = x[i, k]
            if v < lo[m, k]:
                lo[m, k] = v
            if v > hi[m, k]:
                hi[m, k] = v
    return lo, hi


@njit(cache=True)
def _count_below(x, n, node_of, axes, cuts):
    n_nodes = axes.shape[0]
    below = np.zeros(n_nodes, dtype=np.int64)
    total = np.zeros(n_nodes, dtype=np.int64)
    for i in range(n):
        m = node_of[i]
        if m < 0:
            continue
        total[m] += 1
        if x[i, axes[m]] < cuts[m]:
            below[m] += 1
    return below, total


@njit(cache=True)
def _count_below_each(x, n, node_of, axes, cands):
    """below[m, j] = number of local particles of node m with x[axis_m] < cands[m, j];
    cands (n_nodes, S) non-decreasing along each row. Returns (n_nodes, S) int64."""
    n_nodes, s = cands.shape
    hist = np.zeros((n_nodes, s + 1), dtype=np.int64)  # hist[m, k]: k candidates <= x
    for i in range(n):
        m = node_of[i]
        if m < 0:
            continue
        hist[m, np.searchsorted(cands[m], x[i, axes[m]], side="right")] += 1
    below = np.zeros((n_nodes, s), dtype=np.int64)
    for m in range(n_nodes):
        run = 0
        for j in range(s):
            run += hist[m, j]  # x < cands[m, j] <=> fewer than j + 1 candidates <= x
            below[m, j] = run
    return below


def rcb(comm, x, n):
    """Collective RCB partition of the particles x[:n] of all ranks into comm.size boxes."""
    P = comm.size
    b = x.shape[1]
    if P == 1:
        return Partition.whole_space(b)
    axis, cut, left, right = [], [], [], []
    # active nodes at this level: (tree node id, first rank, n ranks, box lo, box hi)
    root_lo = np.full(b, -np.inf)
    root_hi = np.full(b, np.inf)
    lo_box = np.zeros((P, b))
    hi_box = np.zeros((P, b))
    axis.append(0), cut.append(0.0), left.append(0), right.append(0)
    active = [(0, 0, P, root_lo, root_hi)]
    node_of = np.zeros(n, dtype=np.int64)  # index into `active` of each local particle
    while active:
        na = len(active)
        lo, hi = _node_bbox(x, n, node_of, na)
        g = comm.allreduce(np.concatenate([lo.ravel(), -hi.ravel()]), op="min")
        glo = g[: na * b].reshape(na, b)
        ghi = -g[na * b:].reshape(na, b)
        ext = np.where(np.isfinite(ghi - glo), ghi - glo, 0.0)
        axes = np.argmax(ext, axis=1).astype(np.int64)
        a_lo = np.array([glo[m, axes[m]] if np.isfinite(glo[m, axes[m]]) else 0.0 for m in range(na)])
        a_hi = np.array([ghi[m, axes[m]] if np.isfinite(ghi[m, axes[m]]) else 0.0 for m in range(na)])
        _, total = _count_below(x, n, node_of, axes, a_lo)
        total = comm.allreduce(total, op="sum")
        target = np.array([total[m] * (active[m][2] // 2) // active[m][2] for m in range(na)])
        # multisection on the cut value: smallest cut with count(x < cut) >= target, keeping
        # count(x < c_lo) < target <= count(x < c_hi)
        c_lo = a_lo.copy()
        c_hi = np.nextafter(a_hi, np.inf)
        fractions = np.arange(1, _SECTIONS + 1) / _SECTIONS  # exact: a power of two
        for _ in range(_ROUNDS):
            # candidates (na, _SECTIONS), non-decreasing along a row, the last = c_hi
            cands = np.minimum(c_lo[:, None] + (c_hi - c_lo)[:, None] * fractions[None, :], c_hi[:, None])
            cands[:, -1] = c_hi
            below = comm.allreduce(_count_below_each(x, n, node_of, axes, cands), op="sum")
            for m in range(na):
                # the first count >= target; the last section if none is (non-finite coordinates
                # are below no candidate: the cut then stays at c_hi, as bisection's did)
                j = min(int(np.searchsorted(below[m], target[m], side="left")), _SECTIONS - 1)
                c_lo[m] = c_lo[m] if j == 0 else cands[m, j - 1]
                c_hi[m] = cands[m, j]
        cuts = c_hi
        new_active = []
        child_of = np.full((na, 2), -1, dtype=np.int64)
        for m, (tid, r0, nr, blo, bhi) in enumerate(active):
            nl = nr // 2
            ax = int(axes[m])
            axis[tid] = ax
            cut[tid] = float(cuts[m])
            for side, (rr, nn) in enumerate(((r0, nl), (r0 + nl, nr - nl))):
                clo, chi = blo.copy(), bhi.copy()
                if side == 0:
                    chi[ax] = cuts[m]
                else:
                    clo[ax] = cuts[m]
                if nn == 1:
                    code = -1 - rr
                    lo_box[rr], hi_box[rr] = clo, chi
                else:
                    code = len(axis)
                    axis.append(0), cut.append(0.0), left.append(0), right.append(0)
                    child_of[m, side] = len(new_active)
                    new_active.append((code, rr, nn, clo, chi))
                if side == 0:
                    left[tid] = code
                else:
                    right[tid] = code
        node_of = _descend(x, n, node_of, axes, cuts, child_of)
        active = new_active
    return Partition(np.array(axis, np.int64), np.array(cut), np.array(left, np.int64),
                     np.array(right, np.int64), lo_box, hi_box)


@njit(cache=True)
def _descend(x, n, node_of, axes, cuts, child_of):
    out = np.empty(n, dtype=np.int64)
    for i in range(n):
        m = node_of[i]
        if m < 0:
            out[i] = -1
            continue
        side = 0 if x[i, axes[m]] < cuts[m] else 1
        out[i] = child_of[m, side]
    return out


@njit(cache=True)
def ghost_destinations(x, n_local, me, lo, hi, r_ghost):
    """Which other ranks need each local particle as a ghost.

    Particle i goes to rank s != me when its distance to box s is below r_ghost. Returns
    (offsets (P+1,), idx): rank s gets local rows idx[offsets[s]:offsets[s+1]].
    """
    P = lo.shape[0]
    b = x.shape[1]
    counts = np.zeros(P, dtype=np.int64)
    pairs_i = np.empty(max(16, n_local), dtype=np.int64)
    pairs_s = np.empty(max(16, n_local), dtype=np.int64)
    m = 0
    rg2 = r_ghost * r_ghost
    for i in range(n_local):
        # depth inside my own box: particles deeper than r_ghost are nobody else's ghost
        depth = np.inf
        for k in range(b):
            dd = min(x[i, k] - lo[me, k], hi[me, k] - x[i, k])
            if dd < depth:
                depth = dd
        if depth >= r_ghost:
            continue
        for s in range(P):
            if s == me:
                continue
            d2 = 0.0
            for k in range(b):
                v = x[i, k]
                if v < lo[s, k]:
                    d2 += (lo[s, k] - v) ** 2
                elif v > hi[s, k]:
                    d2 += (v - hi[s, k]) ** 2
            if d2 < rg2:
                if m == pairs_i.shape[0]:
                    ni = np.empty(2 * m, dtype=np.int64)
                    ni[:m] = pairs_i
                    pairs_i = ni
                    ns = np.empty(2 * m, dtype=np.int64)
                    ns[:m] = pairs_s
                    pairs_s = ns
                pairs_i[m] = i
                pairs_s[m] = s
                counts[s] += 1
                m += 1
    offsets = np.zeros(P + 1, dtype=np.int64)
    for s in range(P):
        offsets[s + 1] = offsets[s] + counts[s]
    fill = offsets[:-1].copy()
    idx = np.empty(m, dtype=np.int64)
    for q in range(m):
        s = pairs_s[q]
        idx[fill[s]] = pairs_i[q]
        fill[s] += 1
    return offsets, idx
