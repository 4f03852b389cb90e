"""The iteration loop on a spatially decomposed particle cloud: DAHA, AHA, NAP, NAV.

One iteration of DAHA / AHA, n -> n+1 (every rank, in lock step):

    step        kernels: lambda^n = max(0, lambda^{n-1} + beta phi(X^n))       (2.10b)
                         X^{n+1} from X^n, X^{n-1}, lambda^n, Xbar^n            (2.10a)
    reduce      ONE allreduce: exact sum X^{n+1} (-> Xbar^{n+1}), ||X^{n+1}-X^n||^2, ||X^n||^2,
                active pair count; largest step, max overlap, max particles per rank
    rebuild     when particles may have moved more than skin/2 since the rows were built:
                exchange (migrate with pair history), rebalance when max/mean particles per
                rank > neighbor.rebalance, borders, pair rows
    or forward  ghost positions X^{n+1} from their owners
    stop        ||X^{n+1} - X^n|| / ||X^n|| < eps   (4.3)

NAP and NAV run the same step/reduce/forward cycle for each inner iteration, with the
constraints linearised about the outer iterate X^p (see ``_outer_step``).

Every decision (stop, rebuild, rebalance, numerical failure) is taken from allreduced numbers,
so all ranks take it on the same iteration. Sums are exact (see ``exactsum``), pair sums run in
partner-gid order and the initial data is a function of gid only: the trajectory is bitwise
the same on any number of ranks.

Stopping criterion (4.3) in math: with X^n in R^{bN},
    ||X^{n+1} - X^n||_2 / ||X^n||_2 < eps.
It is a relative change, not a distance to the optimum: it can fire while the configuration is
still creeping (slow modes), and it is not translation invariant.
"""

import math
import time

import numpy as np

from . import comm as comm_mod
from . import config, domain, exactsum, init, kernels, metrics, neighbors
from .state import State, gather_rows


class NumericalError(RuntimeError):
    """NaN, Inf or divergence in the state."""


class TooDenseError(RuntimeError):
    """The pair rows of the current configuration would not fit in memory."""


# bytes per pair-row entry at the peak of a build (entry 12 B, growth copies, temporaries)
_BYTES_PER_ENTRY_PEAK = 40


def _available_memory_bytes():
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 2 ** 40


class Solver:
    """Owns the state of one rank and advances it. ``comm`` is a ``comm.Comm``."""

    def __init__(self, scene, comm):
        self.scene = scene
        self.comm = comm
        self.dim = scene["dim"]
        self.n = scene["n"]
        m = scene["method"]
        self.method = m["name"]
        self.form = m["form"]
        self.beta = float(m["beta"])
        self.nested = self.method in ("nap", "nav")
        if self.nested:
            self.coeffs = kernels.nested_coefficients(self.method, m["alpha"], m["tau"])
            self._nested_kernel = kernels.nested_step(self.method, self.form)
        else:
            self.coeffs = kernels.coefficients(self.method, m["alpha"], m["beta"], m["gamma"], m["c"])
        # the one-pass kernel steps DAHA/AHA; with zero coefficients it also serves the final
        # metrics of every method
        self._kernel = kernels.multipliers_and_step(self.form, self.dim)
        self.d_max = config.d_max(scene)
        self.skin = float(scene["neighbor"]["skin"]) * self.d_max
        self.r_ghost = self.d_max + self.skin
        self.state = State(self.dim, self.n)
        self.partition = domain.Partition.whole_space(self.dim)
        self.plan = comm_mod.GhostPlan.empty()
        self.xbar = np.zeros(self.dim)
        self.counters = {"rebuilds": 0, "rebalances": 0, "far_ghosts": 0, "max_imbalance": 1.0,
                         "inner_iterations": 0}
        self.last = {}  # last reduced figures
        self._acc = exactsum.new_accumulator(self.dim + 2)
        self._maxima = np.zeros(kernels.N_MAX)
        self._disp_bound = 0.0  # upper bound of the displacement since the rows were built
        # pair-row budget of this rank: neighbor.max_pair_gib, or its share of the node's
        # available memory (under a batch system's memory limit, set the key)
        gib = scene["neighbor"]["max_pair_gib"]
        budget = gib * 2 ** 30 if gib is not None else _available_memory_bytes() / comm.ranks_per_node
        self._max_entries = int(budget / _BYTES_PER_ENTRY_PEAK)

    # ---- set-up ----------------------------------------------------------------------------
    def initialise(self):
        """Initial data for this rank's gid block, then partition, migrate, ghosts and rows."""
        r, P, N = self.comm.rank, self.comm.size, self.n
        gids = np.arange(N * r // P, N * (r + 1) // P, dtype=np.int64)
        x = init.positions(self.scene, gids)
        p = self.scene["particles"]
        dmax = p["diameter_max"] if p["diameter_max"] is not None else p["diameter"]
        diam = init.diameters(self.scene["seed"], gids, float(p["diameter"]), float(dmax))
        st = self.state
        local = {"x": x, "x_prev": x.copy(), "gid": gids, "diam": diam}
        ghost = {"x": np.zeros((0, self.dim)), "gid": np.zeros(0, np.int64), "diam": np.zeros(0)}
        if self.nested:
            local["x_lin"] = x.copy()
            ghost["x_lin"] = np.zeros((0, self.dim))
        st.set_particles(local, ghost)
        st.pair_offsets = np.zeros(x.shape[0] + 1, dtype=np.int64)
        st.lambda_fresh = True
        st.iteration = 0
        self.rebuild(rebalance=True)
        self.xbar = self._centre_of_mass()
        # compile (or load from cache) the step kernels now, so the loop's timing excludes it
        self._kernel(st.x, st.x_prev, st.x_new, 0, st.diam, st.pair_offsets, st.pair_j,
                     st.pair_lambda, self.xbar, 0.0, 0.0, 0.0, 0.0, self.beta, False,
                     exactsum.new_accumulator(self.dim + 2), np.zeros(kernels.N_MAX))
        if self.nested:
            self._nested_kernel(st.x, st.x_lin, st.x_new, 0, st.diam, st.pair_offsets, st.pair_j,
                                st.pair_lambda, self.xbar, *self.coeffs, self.beta, False,
                                exactsum.new_accumulator(self.dim + 2), np.zeros(kernels.N_MAX))

    def _centre_of_mass(self):
        st = self.state
        acc = exactsum.new_accumulator(self.dim + 1)
        kernels.local_sums(st.x, st.n_local, acc)
        g, _ = self.comm.reduce_fused(acc, np.zeros(0))
        return np.array([exactsum.value(g, k) for k in range(self.dim)]) / self.n

    # ---- one iteration ----------------------------------------------------------------------
    def step(self):
        """Advance one (outer) iteration; returns the reduced figures of this iteration."""
        if self.nested:
            return self._outer_step()
        st = self.state
        a1, a2, a3, a4 = self.coeffs
        fig = self._advance(lambda acc, update: self._kernel(
            st.x, st.x_prev, st.x_new, st.n_local, st.diam, st.pair_offsets, st.pair_j,
            st.pair_lambda, self.xbar, a1, a2, a3, a4, self.beta, update, acc, self._maxima))
        self.xbar = fig.pop("xbar")
        st.iteration += 1
        fig["iteration"] = st.iteration
        self.last = fig
        return fig

    def _advance(self, kernel):
        """One kernel pass and everything after it: the fused reduction, the numerical guard,
        the rotation X^{n-1}, X^n <- X^n, X^{n+1}, and fresh ghosts (forward or rebuild).

        kernel(acc, update_lambda) runs the pass on the current arrays and returns the number
        of active row entries. Returns the figures, with "xbar" of the new positions.
        """
        st = self.state
        acc = self._acc
        acc[:] = 0
        n_active = kernel(acc, not st.lambda_fresh)
        st.lambda_fresh = False
        sums = np.append(acc.ravel(), np.int64(n_active))
        maxima = np.append(self._maxima, float(st.n_local))
        g_sums, g_max = self.comm.reduce_fused(sums, maxima)
        g_acc = g_sums[:-1].reshape(acc.shape)
        b = self.dim
        if any(g_acc[q, exactsum.NBINS] != 0 for q in range(b + 2)) or not np.all(np.isfinite(g_max)):
            raise NumericalError(
                f"non-finite or diverging positions at iteration {st.iteration + 1} "
                f"(NaN/Inf, or |X|^2 beyond {exactsum.RANGE:.3g}); lower alpha/beta or raise c")
        dx2 = exactsum.value(g_acc, b)
        xx2 = exactsum.value(g_acc, b + 1)
        st.rotate()
        rel = math.sqrt(dx2 / xx2) if xx2 > 0 else (0.0 if dx2 == 0 else math.inf)
        max_step = math.sqrt(g_max[kernels.MAX_STEP2])
        fig = {
            "xbar": np.array([exactsum.value(g_acc, k) for k in range(b)]) / self.n,
            "relative_change": rel,
            "change2": dx2,
            "max_overlap": float(g_max[kernels.MAX_OVERLAP]),
            "active_pairs": int(g_sums[-1]) // 2,
            "max_step": max_step,
            "max_local": int(g_max[2]),
        }
        fig["imbalance"] = fig["max_local"] * self.comm.size / self.n
        self.counters["max_imbalance"] = max(self.counters["max_imbalance"], fig["imbalance"])
        self._refresh_ghosts(max_step)
        return fig

    def _refresh_ghosts(self, max_move):
        """After local positions moved by at most ``max_move`` (a reduced value): fresh ghosts,
        by forward, or by a rebuild if the pair rows may have gone stale.

        Pair rows stay valid while no particle has moved more than skin/2 since the build.
        The sum of the largest moves bounds that displacement (triangle inequality) without
        reading x_build every iteration; only when the bound trips is the exact displacement
        measured (one more allreduce), and the rows rebuilt if it really exceeds skin/2.
        """
        st = self.state
        self._disp_bound += max_move
        if self._disp_bound > 0.5 * self.skin:
            local = neighbors.max_displacement2(st.x, st.x_build, st.n_local)
            exact = math.sqrt(self.comm.allreduce(np.array([local]), op="max")[0])
            if exact > 0.5 * self.skin or not math.isfinite(exact):
                self.rebuild()
                return
            self._disp_bound = exact
        comm_mod.forward(self.comm, self.plan, st.x, st.n_local)

    def _outer_step(self):
        """One outer iteration p -> p+1 of NAP (2.16) or NAV (2.17).

        The constraints are linearised about X^p (kept in x_lin, ghosts included, and carried
        through rebuilds). Inner steps run until the inner criterion, (4.1) for NAP:
        ||X^{p,n+1} - X^{p,n}|| / ||X^{p,n}|| < eps_inner, (4.2) for NAV:
        ||V^{p,n+1} - V^{p,n}|| / ||X^p|| < eps_inner / tau, or l_inner steps. Then
        lambda^{p+1} from the last inner iterate, and the outer criterion (4.3) is measured.
        NAV's inner variable is Y = X^p + tau V; it starts from V^{p,0} = V^p, i.e.
        Y = X^p + (X^p - X^{p-1}) (V^0 = 0).
        """
        st = self.state
        m = self.scene["method"]
        n = st.n_local
        st.x_lin[:] = st.x  # X^p, ghosts are current
        nav = self.method == "nav"
        xbar_p = self.xbar.copy()
        if nav:
            acc = exactsum.new_accumulator(self.dim + 1)
            kernels.local_sums(st.x, n, acc)
            g, _ = self.comm.reduce_fused(acc, np.zeros(0))
            norm_p = math.sqrt(exactsum.value(g, self.dim))  # ||X^p||, for (4.2)
            st.x[:n] = 2.0 * st.x_lin[:n] - st.x_prev[:n]
            # the warm start moves every particle by |X^p - X^{p-1}|: it counts for the rows
            jump2 = neighbors.max_displacement2(st.x, st.x_lin, n)
            self._refresh_ghosts(math.sqrt(self.comm.allreduce(np.array([jump2]), op="max")[0]))
        cy, cp, cw, cf = self.coeffs
        inner = 0
        fig = {}
        for inner in range(1, int(m["l_inner"]) + 1):
            fig = self._advance(lambda acc, update: self._nested_kernel(
                st.x, st.x_lin, st.x_new, st.n_local, st.diam, st.pair_offsets, st.pair_j,
                st.pair_lambda, xbar_p if nav else self.xbar, cy, cp, cw, cf, self.beta, update,
                acc, self._maxima))
            self.xbar = fig.pop("xbar")
            if nav:
                rel_inner = math.sqrt(fig["change2"]) / norm_p if norm_p > 0 else 0.0
            else:
                rel_inner = fig["relative_change"]
            if rel_inner < m["eps_inner"]:
                break
        self.counters["inner_iterations"] += inner
        # (2.16b) / (2.17b) for the last inner iterate: lambda^{p+1}; positions are discarded
        acc = exactsum.new_accumulator(self.dim + 2)
        self._nested_kernel(st.x, st.x_lin, st.x_new, st.n_local, st.diam, st.pair_offsets,
                            st.pair_j, st.pair_lambda, self.xbar, cy, cp, cw, cf, self.beta,
                            not st.lambda_fresh, acc, self._maxima)
        st.lambda_fresh = True
        # outer criterion (4.3): ||X^{p+1} - X^p|| / ||X^p||
        acc = exactsum.new_accumulator(2)
        kernels.change_sums(st.x, st.x_lin, st.n_local, acc)
        g, _ = self.comm.reduce_fused(acc, np.zeros(0))
        d2, p2 = exactsum.value(g, 0), exactsum.value(g, 1)
        st.x_prev[:st.n_local] = st.x_lin[:st.n_local]  # X^{p}, for NAV's V^{p+1}
        st.iteration += 1
        fig["relative_change"] = math.sqrt(d2 / p2) if p2 > 0 else (0.0 if d2 == 0 else math.inf)
        fig["iteration"] = st.iteration
        fig["inner_iterations"] = inner
        self.last = fig
        return fig

    # ---- rebuild: exchange, (balance), borders, rows -----------------------------------------
    def rebuild(self, rebalance=False):
        """Exchange (and rebalance), sort locals by cell, borders, pair rows. Collective."""
        st, comm = self.state, self.comm
        hist = neighbors.history(st.n_local, st.gid, st.pair_offsets, st.pair_j, st.pair_lambda)
        part = st.local_fields()
        if comm.size > 1:
            if rebalance:
                self.partition = domain.rcb(comm, part["x"], part["x"].shape[0])
                self.counters["rebalances"] += 1
            part, hist = self._exchange(part, hist)
            # migration may have unbalanced the load: check now (one small allreduce, only at
            # rebuilds) rather than wait for the next rebuild, which may be far away
            n_here = part["x"].shape[0]
            max_local = comm.allreduce(np.array([n_here], dtype=np.int64), op="max")[0]
            if not rebalance and max_local * comm.size > self.scene["neighbor"]["rebalance"] * self.n:
                self.partition = domain.rcb(comm, part["x"], n_here)
                self.counters["rebalances"] += 1
                part, hist = self._exchange(part, hist)
        # local particles in cell order: neighbours sit close in memory for the step kernel
        perm = neighbors.spatial_order(part["x"], part["x"].shape[0], self.r_ghost)
        part = {k: v[perm] for k, v in part.items()}
        h_off, h_idx = gather_rows(hist[0], perm)
        hist = (h_off, hist[1][h_idx], hist[2][h_idx])
        ghost_keys = ("x", "gid", "diam") + (("x_lin",) if "x_lin" in part else ())
        if comm.size > 1:
            ghost = self._borders(part, ghost_keys, hist[1])
        else:
            ghost = {k: part[k][:0] for k in ghost_keys}
        lam_fresh = st.lambda_fresh
        st.set_particles(part, ghost)
        st.lambda_fresh = lam_fresh
        st.pair_offsets, st.pair_j, st.pair_lambda, missing = neighbors.build_rows(
            st.x, st.n_local, st.n_total, st.gid, st.diam, self.skin, *hist,
            max_entries=self._max_entries)
        too_dense = self.comm.allreduce(np.array([1 if missing < 0 else 0]), op="max")[0]
        if too_dense:
            raise TooDenseError(
                f"the configuration is too dense for memory: the pair rows of {self.n} spheres "
                f"would need more than {self._max_entries * _BYTES_PER_ENTRY_PEAK / 2**30:.1f} GiB "
                f"on a rank; spread the start (raise init.sigma, now {self.scene['init']['sigma']:g}), "
                f"use init.kind = \"lattice\", or run on more nodes (limit: neighbor.max_pair_gib)")
        if missing:
            raise RuntimeError(f"internal error: {missing} pair partners with lambda > 0 are missing "
                               f"on rank {comm.rank} after the ghost exchange")
        st.x_build = st.x[: st.n_local].copy()
        self._disp_bound = 0.0
        self.counters["rebuilds"] += 1

    def _exchange(self, part, hist):
        """Move every particle to the owner of its position; its pair history moves with it.

        part: dict of per-particle arrays (local rows); hist: (offsets, partner gid, lambda).
        Returns the new (part, hist).
        """
        comm = self.comm
        hist_off, hist_gid, hist_lam = hist
        n = part["x"].shape[0]
        owners = self.partition.owners(part["x"], n)
        order = np.argsort(owners, kind="stable")
        movers = order[owners[order] != comm.rank]
        stay = np.flatnonzero(owners == comm.rank)
        dest = owners[movers]
        counts = np.bincount(dest, minlength=comm.size).astype(np.int64)
        h_off, h_idx = gather_rows(hist_off, movers)
        h_counts = np.diff(h_off)
        h_per_rank = np.bincount(dest, weights=h_counts, minlength=comm.size).astype(np.int64)
        send = {k: v[movers] for k, v in part.items()}
        send.update({"h_count": h_counts, "h_gid": hist_gid[h_idx], "h_lam": hist_lam[h_idx]})
        send_counts = {k: counts for k in part}
        send_counts.update({"h_count": counts, "h_gid": h_per_rank, "h_lam": h_per_rank})
        got, _ = comm.alltoallv(send, send_counts)
        s_off, s_idx = gather_rows(hist_off, stay)
        counts_all = np.concatenate([np.diff(s_off), got["h_count"]])
        new_off = np.zeros(counts_all.shape[0] + 1, dtype=np.int64)
        np.cumsum(counts_all, out=new_off[1:])
        new_part = {k: np.concatenate([v[stay], got[k]]) for k, v in part.items()}
        return new_part, (new_off, np.concatenate([hist_gid[s_idx], got["h_gid"]]),
                          np.concatenate([hist_lam[s_idx], got["h_lam"]]))

    def _borders(self, part, keys, hist_gid):
        """Ghosts: particles within r_ghost of this rank's box, plus any pair-history partner
        (lambda > 0) that is further away; those are requested from their owners.

        Returns a dict of the ghosts' ``keys`` arrays; sets self.plan for ``forward``.
        """
        comm = self.comm
        x, gid = part["x"], part["gid"]
        n_local = x.shape[0]
        p = self.partition
        offsets, idx = domain.ghost_destinations(x, n_local, comm.rank, p.lo, p.hi, self.r_ghost)
        fields = {k: part[k] for k in keys}
        plan, got = comm_mod.borders(comm, offsets, idx, fields)
        present = np.concatenate([gid, got["gid"]])
        missing = neighbors.missing_partners(present.shape[0], present, hist_gid)
        requests = comm.allgather_object(missing)
        if any(len(r) for r in requests):
            # far partners: each owner adds the requested particles to its send lists
            lookup = np.argsort(gid)
            sorted_gid = gid[lookup]
            ranks = [np.repeat(np.arange(comm.size), np.diff(offsets))]
            rows = [idx]
            for r, req in enumerate(requests):
                if r == comm.rank or len(req) == 0 or n_local == 0:
                    continue
                pos = np.minimum(np.searchsorted(sorted_gid, req), n_local - 1)
                mine = lookup[pos[sorted_gid[pos] == req]]
                mine = np.setdiff1d(mine, idx[offsets[r]:offsets[r + 1]])
                ranks.append(np.full(mine.shape[0], r, dtype=np.int64))
                rows.append(mine.astype(np.int64))
            self.counters["far_ghosts"] += int(sum(len(r) for r in requests))
            ranks = np.concatenate(ranks)
            rows = np.concatenate(rows)
            o = np.argsort(ranks, kind="stable")
            idx = rows[o]
            offsets = np.zeros(comm.size + 1, dtype=np.int64)
            np.cumsum(np.bincount(ranks, minlength=comm.size), out=offsets[1:])
            plan, got = comm_mod.borders(comm, offsets, idx, fields)
        self.plan = plan
        return got

    # ---- end of run --------------------------------------------------------------------------
    def finish(self):
        """Bring lambda up to date with the final X (2.10b) and return final figures:
        max overlap, W, packing density about the centre of mass, active pairs."""
        st = self.state
        # DAHA/AHA: one (2.10b) pass brings lambda^{n-1} to lambda^n (the step it also computes
        # is discarded); NAP/NAV end every outer iteration with fresh multipliers. Either way
        # the pass measures the max overlap.
        update = not st.lambda_fresh
        a = self.coeffs if update else (0.0, 0.0, 0.0, 0.0)
        self._kernel(st.x, st.x_prev, st.x_new, st.n_local, st.diam, st.pair_offsets, st.pair_j,
                     st.pair_lambda if update else st.pair_lambda.copy(), self.xbar, *a, self.beta,
                     update, exactsum.new_accumulator(self.dim + 2), self._maxima)
        st.lambda_fresh = True
        w_acc = exactsum.new_accumulator(1)
        kernels.centred_sums(st.x, st.n_local, self.xbar, w_acc)
        n_active = int(np.count_nonzero(st.pair_lambda > 0))
        g, gmax = self.comm.reduce_fused(np.append(w_acc.ravel(), n_active), self._maxima[:2].copy())
        sum_sq = exactsum.value(g[:-1].reshape(w_acc.shape), 0)
        W = 0.5 * sum_sq
        r_gyr = math.sqrt(sum_sq / self.n)
        radii = np.array([r_gyr]) if r_gyr > 0 else np.array([self.d_max])
        c_acc = exactsum.new_accumulator(radii.shape[0])
        metrics.covered_measure(st.x, st.diam, st.n_local, self.xbar, radii, c_acc)
        gc, _ = self.comm.reduce_fused(c_acc, np.zeros(0))
        density = exactsum.value(gc, 0) / metrics.ball_measure(self.dim, radii[0])
        return {
            "max_overlap": float(gmax[kernels.MAX_OVERLAP]),
            "W": W,
            "density": density,
            "density_radius": float(radii[0]),
            "active_pairs": int(g[-1]) // 2,
        }

    def gather(self, root=0):
        """All particles and lambda > 0 pairs on ``root``, in gid order (for tests and small N).

        Returns dict(gid, x, x_prev, diam, pairs=(gid_i, gid_j, lambda) with gid_i < gid_j) on
        root, None elsewhere.
        """
        st = self.state
        n = st.n_local
        gi, gj, lam = st.local_pairs()
        mine = {"gid": st.gid[:n], "x": st.x[:n], "x_prev": st.x_prev[:n], "diam": st.diam[:n],
                "pi": gi, "pj": gj, "pl": lam}
        parts = [mine] if self.comm.size == 1 else self.comm.mpi.gather(mine, root=root)
        if self.comm.rank != root:
            return None
        cat = {k: np.concatenate([p[k] for p in parts]) for k in mine}
        o = np.argsort(cat["gid"])
        keep = cat["pi"] < cat["pj"]
        po = np.lexsort((cat["pj"][keep], cat["pi"][keep]))
        return {"gid": cat["gid"][o], "x": cat["x"][o], "x_prev": cat["x_prev"][o],
                "diam": cat["diam"][o],
                "pairs_gid": np.stack([cat["pi"][keep][po], cat["pj"][keep][po]], axis=1),
                "pairs_lambda": cat["pl"][keep][po]}


def run(scene, comm, on_progress=None):
    """Run a scene to convergence or max_iter. Returns (solver, result dict).

    on_progress(figures, elapsed) is called on every rank after each iteration (the caller
    decides what to print, and where).
    """
    solver = Solver(scene, comm)
    t0 = time.perf_counter()
    solver.initialise()
    t_setup = time.perf_counter() - t0
    eps = scene["stop"]["eps"]
    max_iter = scene["stop"]["max_iter"]
    converged = False
    fig = {"relative_change": math.nan}
    t_loop = time.perf_counter()
    while solver.state.iteration < max_iter:
        fig = solver.step()
        if on_progress is not None:
            on_progress(fig, time.perf_counter() - t_loop)
        if eps > 0 and fig["relative_change"] < eps:
            converged = True
            break
    loop_seconds = time.perf_counter() - t_loop
    final = solver.finish()
    iters = solver.state.iteration
    # work: particle-iterations of the kernel, inner ones for the nested methods
    work = solver.n * (solver.counters["inner_iterations"] if solver.nested else iters)
    result = {
        "iterations": iters,
        "converged": converged,
        "relative_change": fig["relative_change"],
        "setup_seconds": t_setup,
        "loop_seconds": loop_seconds,
        "particle_iterations_per_second": work / loop_seconds if loop_seconds > 0 else 0.0,
        **final,
        **solver.counters,
    }
    return solver, result
