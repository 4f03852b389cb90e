"""What a run reports and hands over, from a ``Solver`` (collective calls): the metrics pass
(max overlap, KKT residual, complementarity, W, per-sphere pressure), the final figures, the
state by gid (``BlockState``) and gathers for tests and small N.
"""

import math

import numpy as np

from mpipack.parallel import comm as comm_mod
from mpipack.kernels import daha as kernels, metrics, potential
from mpipack.parallel import neighbors
from mpipack.parallel.reduction import Reduction
from mpipack.parallel.state import BlockState


def measure(s, finalize=False, empty=False, overlap_a=True, pair_force=None):
    """One metrics pass (collective): max overlap, KKT residual, complementarity, W, and with
    ``overlap_a`` the paper's A (lens areas of every overlapping pair: the costly part; NaN
    without).

    The multipliers are those of the current X: when the state holds lambda^{n-1} (DAHA/AHA
    between iterations) the pass applies (2.10b) on the fly; it stores the result only with
    ``finalize`` (the end of a run), so a check in the middle of a run changes nothing.
    Returns the reduced figures and the per-sphere fields (a dict of arrays of n_local rows):
    pressure mu_i = sum_j lambda_ij, active contacts, and net_force |g_i|, the sphere's row of
    the KKT residual, g_i = (X_i - Xbar) + sum_j lambda_ij grad_{X_i} phi_ij. ``pair_force``
    (float64, one per row entry of the local spheres) receives each entry's multiplier, the one
    the pressure sums (for the snapshots' contact pairs). ``empty`` runs the
    pass over no particle (it compiles the kernel, and still reduces: collective).

    max_net_force = max_i |g_i|, and net_force_share = max_i |g_i|^2 / sum_i |g_i|^2, the part
    of the squared residual on the single worst sphere: near 1 / N when the residual is spread
    over the packing (multipliers off by a common factor, a breathing mode), large when a few
    spheres carry it (a local rearrangement still under way; docs/research/convergence.md, section 3i).

    Force imbalance = ||grad W + sum lambda grad phi|| / ||c||, c_i = sum_j lambda_ij
    |grad_i phi_ij|: the same net forces relative to the contact forces the spheres carry
    (reported, not a criterion of the certificate). In a trapped packing of radius R (in
    diameters) the contact forces grow like the pressure, ~R^2, and the pull of W like R, so
    that a packing balanced to the same fraction of its contact forces has a KKT residual
    ~R times larger: at N = 1e5 in 2D about 7 times that of N = 2000.

    KKT residual = ||grad W + sum lambda grad phi|| / ||grad W|| over all spheres (2.4), with
    the multipliers of (2.4) (NAV's are tau times its own, see (2.6)); pressure likewise. Under
    the fire-al schedule's augmented Lagrangian the multipliers are the force multipliers
    max(0, lambda + rho phi) of pairs in contact to stop.overlap (``FireALSchedule.force_multiplier``):
    the forces the spheres move with, the first-order multiplier estimate that augmented
    Lagrangian codes test stationarity with; the stored lambda is only the last dual step's.
    """
    st = s.state
    mode, pen, floor = multiplier_mode(s, finalize)
    red = Reduction().add_exact("met", [("kkt2", 1), ("gw2", 1), ("lens", 1), ("spheres", 1), ("cf2", 1),
                                        ("wpot", 1)]) \
        .add_max("met", [("overlap", 1), ("complementarity", 1), ("max_lambda", 1), ("max_net_force", 1)]) \
        .add_count("active").begin()
    pressure = np.zeros(st.n_local)
    contacts = np.zeros(st.n_local, dtype=np.int32)
    net_force = np.zeros(st.n_local)
    wall_force = np.zeros(st.n_local if st.walls.shape[0] else 0)
    n_active = s.metrics_kernel(st.x, 0 if empty else st.n_local, st.diam, st.gid, st.pair_offsets, st.pair_j,
                                st.pair_lambda, st.walls, st.wall_lambda, s.xbar, s.pot, s.method.beta, mode, s.method.kkt_lambda_scale, pen, floor,
                                s.scene.stop.overlap, overlap_a,
                                red.acc("met"), red.maxima("met"), pressure, contacts, net_force,
                                np.empty(0) if pair_force is None else pair_force, wall_force)
    if mode == kernels.LAMBDA_UPDATE:
        st.lambda_fresh = True
    red.set_count("active", n_active)
    red.reduce(s.comm)
    kkt2, gw2, cf2 = red.value("kkt2"), red.value("gw2"), red.value("cf2")
    fig = {
        "max_overlap": red.max("overlap"),
        # W: 1/2 sum |X_i - A|^2 (centre, point), or gravity's g sum m_i (h_i - h_0)
        "W": s.pot[potential.POT_G] * red.value("wpot") if s.gravity else 0.5 * gw2,
        "grad_w2": gw2,
        "kkt_residual": math.sqrt(kkt2 / gw2) if gw2 > 0 else (0.0 if kkt2 == 0 else math.inf),
        # the same residual relative to the contact forces the spheres carry (scale-free in N:
        # at a KKT point the contact forces grow like the pressure, ~R^2, the pull of W like R)
        "force_imbalance": math.sqrt(kkt2 / cf2) if cf2 > 0 else (0.0 if kkt2 == 0 else math.inf),
        "complementarity": red.max("complementarity"),
        # the paper's A (Definition 4.1): sum_{i<j} |B_i ∩ B_j| / (N sum_i |B_i|)
        "overlap_A": (red.value("lens") / (s.n * red.value("spheres"))
                      if overlap_a and red.value("spheres") > 0 else math.nan),
        "max_lambda": red.max("max_lambda"),
        "max_net_force": red.max("max_net_force"),
        "net_force_share": (red.max("max_net_force") ** 2 / kkt2 if kkt2 > 0 else 0.0),
        "active_pairs": red.count("active") // 2,
        "radius_of_gyration": math.sqrt(gw2 / s.n),
    }
    fields = {"pressure": pressure, "contacts": contacts, "net_force": net_force}
    if st.walls.shape[0]:
        fields["wall_force"] = wall_force
    return fig, fields


def _radius_of_gyration(s):
    """(sqrt(sum |X_i - Xbar|^2 / N), Xbar): the radius of gyration about the centre of mass
    and that centre (collective)."""
    st = s.state
    red = Reduction().add_exact("sums", [("x", s.dim), ("xx", 1)]).begin()
    kernels.local_sums(st.x, st.n_local, red.acc("sums"))
    red.reduce(s.comm)
    xbar = red.values("x") / s.n
    return math.sqrt(max(red.value("xx") / s.n - float(xbar @ xbar), 0.0)), xbar


def multiplier_mode(s, finalize=False):
    """(lambda_mode, pen, lam_floor): which multipliers are those of the current X (see
    ``measure``; the method's ``multipliers``): pen and lam_floor are the fire-al schedule's
    force multipliers'."""
    return s.method.multipliers(s.state.lambda_fresh, finalize)


def best_kkt(s, fig, target, max_steps=None):
    """The KKT residual of the current X with the best multipliers >= 0 on the pairs in contact
    (``fit.best_kkt``), starting from the run's own; fig: this X's ``measure`` figures;
    max_steps: at most this many fit steps (None: the fit's own bound). Returns (residual,
    fit steps). Collective; changes nothing in the state."""
    from mpipack.stop import fit
    mode, pen, floor = multiplier_mode(s)
    return fit.best_kkt(s, mode, pen, floor, fig["grad_w2"], target, max_steps)


def finish(s):
    """Bring lambda up to date with the final X (2.10b) and return the final figures:
    max overlap, W, KKT residual, packing density about the centre of mass, active pairs."""
    # DAHA/AHA hold lambda^{n-1}: one (2.10b) pass makes it lambda^n; NAP/NAV end every
    # outer iteration with fresh multipliers
    fig, _ = measure(s, finalize=True)
    r_gyr, centre = fig.pop("radius_of_gyration"), s.xbar
    if s.gravity or s.point is not None:  # about the centre of mass, not what W pulls to
        r_gyr, centre = _radius_of_gyration(s)
    radius = r_gyr if r_gyr > 0 else s.d_max
    red = Reduction().add_exact("cover", [("cover", 1)]).begin()
    metrics.covered_measure(s.state.x, s.state.diam, s.state.n_local, centre,
                            np.array([radius]), red.acc("cover"))
    fig["density"] = red.reduce(s.comm).value("cover") / metrics.ball_measure(s.dim, radius)
    fig["density_radius"] = float(radius)
    return fig

def export_state(s):
    """This rank's ``BlockState`` (collective): the state by gid, free of the partition."""
    st = s.state
    part = st.local_fields()
    hist = neighbors.history(st.n_local, st.gid, st.pair_offsets, st.pair_j, st.pair_lambda)
    part, hist = comm_mod.to_gid_blocks(s.comm, s.n, part, hist)
    r, P, N = s.comm.rank, s.comm.size, s.n
    return BlockState(n_global=N, dim=s.dim, gid_lo=N * r // P, x=part["x"],
                      x_prev=part["x_prev"], diam=part["diam"], hist_count=np.diff(hist[0]),
                      hist_gid=hist[1], hist_lambda=hist[2], x_lin=part.get("x_lin"), qn=part.get("qn"),
                      wall_lambda=part.get("wall_lambda"),
                      iteration=st.iteration, lambda_fresh=st.lambda_fresh,
                      counters=dict(s.counters))

def gather(s, root=0):
    """All particles and lambda > 0 pairs on ``root``, in gid order (for tests and small N).

    Returns dict(gid, x, x_prev, diam, pairs_gid (k, 2) with gid_i < gid_j, pairs_lambda)
    on root, None elsewhere.
    """
    st = s.state
    n = st.n_local
    gi, gj, lam = st.local_pairs()
    keep = gi < gj
    got = comm_mod.gather_by_gid(s.comm, {
        "gid": st.gid[:n], "x": st.x[:n], "x_prev": st.x_prev[:n], "diam": st.diam[:n],
        "_ragged": {"pi": gi[keep], "pj": gj[keep], "pl": lam[keep]}}, root=root)
    if got is None:
        return None
    rg = got.pop("_ragged")
    po = np.lexsort((rg["pj"], rg["pi"]))
    got["pairs_gid"] = np.stack([rg["pi"][po], rg["pj"][po]], axis=1)
    got["pairs_lambda"] = rg["pl"][po]
    return got
