"""Rebuild of one rank's particles, ghosts and pair rows on a ``Solver`` (collective).

    exchange   particles migrate to the owner of their position, pair history with them
    balance    a new RCB partition: at the start, and when max/mean particles per rank
               exceeds neighbor.rebalance after a migration
    rows       locals sorted by cell (memory locality), then borders (ghosts, far partners)
               and the Verlet pair rows with lambda from the history

Run when some particle may have moved more than skin/2 since the last build
(``Solver.refresh_ghosts``). A rebuild never changes results: rows hold every pair within
d_ij + skin and every pair with lambda > 0, summed in partner-gid order.
"""

import numpy as np

from mpipack.engine.memory import BYTES_PER_ENTRY_PEAK
from mpipack.errors import TooDenseError
from mpipack.parallel import comm as comm_mod
from mpipack.parallel import domain, neighbors
from mpipack.engine import initial as init
from mpipack.parallel.state import gather_rows
from mpipack.engine.timers import BALANCE, BORDERS, EXCHANGE, ROWS



# neighbor.adaptive_skin: the skin s minimises the cost of an iteration, pair work growing
# like s (the entries of the shell d < r < d + s) and the build's cost spread over the
# (s / 2) / u iterations it lasts at the last period's speed u: s = sqrt(SKIN_COST u d), with
# SKIN_COST = 2 (build cost per sphere) / (pass cost per sphere per unit of skin), measured
# (docs/benchmarks.md, "Cheaper rows, an adaptive skin and a shorter quench"; the method's
# ``skin_cost``, SKIN_COST unless it says otherwise); at least SKIN_MIN d, at most
# neighbor.skin d
SKIN_COST = 5.0
SKIN_MIN = 0.05


def next_skin(rate, d_max, skin_max, cost=None):
    """The skin of the next build, for particles moving by at most ``rate`` an iteration;
    cost: the method's constant (``Method.skin_cost``), None for SKIN_COST."""
    cost = SKIN_COST if cost is None else cost
    return min(skin_max, max(SKIN_MIN * d_max, (cost * rate * d_max) ** 0.5))


def rebuild(s, rebalance=False, hist=None):
    """Exchange (and rebalance), sort locals by cell, borders, pair rows. Collective.

    hist: the locals' pair history (offsets, partner gid, lambda); default: from the rows.
    """
    st, comm, t = s.state, s.comm, s.timers
    if hist is None:
        hist = neighbors.history(st.n_local, st.gid, st.pair_offsets, st.pair_j, st.pair_lambda)
    part = st.local_fields()
    if comm.size > 1:
        if rebalance:
            _balance(s, part)
        part, hist = comm_mod.exchange(comm, s.partition.owners(part["x"], part["x"].shape[0]), part, hist)
        t.lap(EXCHANGE)
        # migration may have unbalanced the load: check now (one small allreduce, only at
        # rebuilds) rather than wait for the next rebuild, which may be far away
        n_here = part["x"].shape[0]
        max_local = comm.allreduce(np.array([n_here], dtype=np.int64), op="max")[0]
        if not rebalance and max_local * comm.size > s.scene.neighbor.rebalance * s.n:
            _balance(s, part)
            part, hist = comm_mod.exchange(comm, s.partition.owners(part["x"], n_here), part, hist)
            t.lap(EXCHANGE)
    # local particles in cell order: neighbours sit close in memory for the step kernel
    perm = neighbors.spatial_order(part["x"], part["x"].shape[0], s.r_ghost)
    part = {k: v[perm] for k, v in part.items()}
    h_off, h_idx = gather_rows(hist[0], perm)
    hist = (h_off, hist[1][h_idx], hist[2][h_idx])
    t.lap(ROWS)
    ghost_keys = ("x", "gid", "diam") + (("x_lin",) if "x_lin" in part else ())
    if comm.size > 1:
        p = s.partition
        offsets, idx = domain.ghost_destinations(part["x"], part["x"].shape[0], comm.rank,
                                                 p.lo, p.hi, s.r_ghost)
        s.plan, ghost, n_far = comm_mod.borders(comm, offsets, idx,
                                                   {k: part[k] for k in ghost_keys}, hist[1])
        s.counters["far_ghosts"] += n_far
        t.lap(BORDERS)
    else:
        ghost = {k: part[k][:0] for k in ghost_keys}
    lam_fresh = st.lambda_fresh
    st.set_particles(part, ghost)
    st.lambda_fresh = lam_fresh
    st.pair_work = None  # made again from the new rows by the method that uses it
    st.pair_offsets, st.pair_j, st.pair_lambda, missing, st.pair_mirror = neighbors.build_rows(
        st.x, st.n_local, st.n_total, st.gid, st.diam, s.skin, *hist,
        max_entries=s.max_pair_entries)
    too_dense = comm.allreduce(np.array([1 if missing < 0 else 0]), op="max")[0]
    if too_dense:
        raise TooDenseError(
            f"the configuration is too dense for memory: the pair rows of {s.n} spheres "
            f"would need more than {s.max_pair_entries * BYTES_PER_ENTRY_PEAK / 2**30:.1f} GiB "
            f"on a rank; spread the start (raise init.sigma, now {init.gaussian_sigma(s.scene):g}), "
            f"use init.kind = \"lattice\", or run on more nodes (limit: neighbor.max_pair_gib)")
    if missing:
        raise RuntimeError(f"internal error: {missing} pair partners with lambda > 0 are missing "
                           f"on rank {comm.rank} after the ghost exchange")
    st.x_build = st.x[: st.n_local].copy()
    s.counters["rebuilds"] += 1
    t.lap(ROWS)

def _balance(s, part):
    s.partition = domain.rcb(s.comm, part["x"], part["x"].shape[0])
    s.counters["rebalances"] += 1
    s.timers.lap(BALANCE)
