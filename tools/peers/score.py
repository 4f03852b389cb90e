"""Scoring of a configuration (x, diam), the same for every code (numpy; scipy if present).

    python score.py FILE.npz [FILE.npz ...]      # one JSON line per file (keys x, diam)

Figures (d_kl = (d_k + d_l) / 2 for a pair k < l at distance r):

- ``max_overlap``: max over pairs of (d_kl - r) / d_kl, 0 when no pair overlaps;
- ``W`` = 1/2 sum_i |X_i - Xbar|^2 (= 1/(2N) sum_{i<j} |X_i - X_j|^2) and ``W_over_N2`` = W / N^2;
- ``density``: packing density in the ball B(Xbar, R_g), R_g = sqrt(mean |X_i - Xbar|^2) the
  radius of gyration: sum_i |B(X_i, d_i/2) ∩ B(Xbar, R_g)| / |B(Xbar, R_g)| (overlaps are
  negligible at the finish line, so the union is taken as the sum);
- ``contacts``: pairs with r < d_kl (1 + 2e-3) (``contacts_per_sphere`` = 2 contacts / N);
- ``overlapping_pairs``: pairs with r < d_kl.

Pairs are found with scipy.spatial.cKDTree when scipy is importable, else with a numpy cell
list; both give the same pairs.
"""

import json
import math
import sys

import numpy as np

CONTACT_TOL = 2e-3


def ball_measure(dim, R):
    return {1: 2.0 * R, 2: math.pi * R * R, 3: 4.0 / 3.0 * math.pi * R ** 3}[dim]


def intersection_measure(dim, s, a, R):
    """|B(p, a) ∩ B(0, R)| with |p| = s, vectorised over s and a (arrays), R a scalar."""
    s = np.asarray(s, dtype=float)
    a = np.broadcast_to(np.asarray(a, dtype=float), s.shape)
    out = np.zeros(s.shape)
    touch = s < a + R
    if dim == 1:
        lo = np.maximum(s - a, -R)
        hi = np.minimum(s + a, R)
        return np.where(touch, np.maximum(0.0, hi - lo), 0.0)
    inside = touch & (s <= np.abs(R - a))
    small = np.minimum(a, R)
    out[inside] = ball_measure(dim, 1.0) * small[inside] ** dim
    lens = touch & ~inside
    if np.any(lens):
        sl, al = s[lens], a[lens]
        if dim == 2:
            c1 = np.clip((sl * sl + al * al - R * R) / (2.0 * sl * al), -1.0, 1.0)
            c2 = np.clip((sl * sl + R * R - al * al) / (2.0 * sl * R), -1.0, 1.0)
            k = (-sl + al + R) * (sl + al - R) * (sl - al + R) * (sl + al + R)
            out[lens] = al * al * np.arccos(c1) + R * R * np.arccos(c2) - 0.5 * np.sqrt(np.maximum(0.0, k))
        else:
            t = al + R - sl
            out[lens] = math.pi * t * t * (sl * sl + 2.0 * sl * (al + R) - 3.0 * (al - R) ** 2) / (12.0 * sl)
    return out


def _pairs_cells(x, rcut):
    """All pairs i < j with |x_i - x_j| < rcut, by a numpy cell list (cells of side rcut)."""
    n, dim = x.shape
    cell = np.floor((x - x.min(axis=0)) / rcut).astype(np.int64)
    shape = cell.max(axis=0) + 1
    strides = np.cumprod(np.concatenate([[1], shape[:-1]]))
    key = cell @ strides
    order = np.argsort(key, kind="stable")
    skey = key[order]
    offsets = np.array(np.meshgrid(*[[-1, 0, 1]] * dim, indexing="ij")).reshape(dim, -1).T
    out_i, out_j = [], []
    for off in offsets:
        nb = cell + off
        ok = np.all((nb >= 0) & (nb < shape), axis=1)
        nkey = nb @ strides
        lo = np.searchsorted(skey, nkey, side="left")
        hi = np.searchsorted(skey, nkey, side="right")
        cnt = np.where(ok, hi - lo, 0)
        ii = np.repeat(np.arange(n), cnt)
        if ii.size == 0:
            continue
        start = np.repeat(lo, cnt)
        rank = np.arange(ii.size) - np.repeat(np.cumsum(cnt) - cnt, cnt)
        jj = order[start + rank]
        keep = ii < jj
        ii, jj = ii[keep], jj[keep]
        d2 = ((x[ii] - x[jj]) ** 2).sum(axis=1)
        keep = d2 < rcut * rcut
        out_i.append(ii[keep])
        out_j.append(jj[keep])
    if not out_i:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    return np.concatenate(out_i), np.concatenate(out_j)


def close_pairs(x, rcut):
    """Pairs (i, j), i < j, with |x_i - x_j| < rcut, as two index arrays."""
    x = np.ascontiguousarray(x, dtype=float)
    if x.shape[0] < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    try:
        from scipy.spatial import cKDTree
    except ImportError:
        return _pairs_cells(x, rcut)
    p = cKDTree(x).query_pairs(rcut, output_type="ndarray")
    if p.shape[0] == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    return p[:, 0].astype(np.int64), p[:, 1].astype(np.int64)


def score(x, diam):
    """The figures of a configuration: positions x (N, b), diameters diam (N,) or a scalar."""
    x = np.asarray(x, dtype=float)
    if x.ndim == 1:
        x = x[:, None]
    n, dim = x.shape
    diam = np.broadcast_to(np.asarray(diam, dtype=float), (n,))
    xbar = x.mean(axis=0)
    dx = x - xbar
    sum_sq = float((dx * dx).sum())
    W = 0.5 * sum_sq
    rg = math.sqrt(sum_sq / n) if n else 0.0
    i, j = close_pairs(x, float(diam.max()) * (1.0 + CONTACT_TOL))
    r = np.sqrt(((x[i] - x[j]) ** 2).sum(axis=1))
    dkl = 0.5 * (diam[i] + diam[j])
    rel = (dkl - r) / dkl
    max_overlap = float(max(0.0, rel.max())) if rel.size else 0.0
    contacts = int(np.count_nonzero(r < dkl * (1.0 + CONTACT_TOL)))
    R = rg if rg > 0 else float(diam.max())
    s = np.sqrt((dx * dx).sum(axis=1))
    covered = float(intersection_measure(dim, s, 0.5 * diam, R).sum())
    return {
        "n": int(n), "dim": int(dim),
        "max_overlap": max_overlap,
        "W": W, "W_over_N2": W / float(n) ** 2,
        "density": covered / ball_measure(dim, R), "radius_of_gyration": rg,
        "contacts": contacts, "contacts_per_sphere": 2.0 * contacts / n,
        "overlapping_pairs": int(np.count_nonzero(r < dkl)),
    }


# ---- the finish line, the same for every code ------------------------------------------------
OVERLAP_TOL = 1e-3   # max overlap <= 1e-3 d_kl
W_TOL = 5e-3         # W within 0.5% of its settled value ...
LOOKBACK = 1.0 / 3.0  # ... judged over the last third of the run (steps or iterations) ...
W_WINDOW = 3         # ... and over at least 3 check intervals


def settled(steps, Ws, w_tol=W_TOL, lookback=LOOKBACK, window=W_WINDOW):
    """Is W settled at the newest check?

    ``steps`` and ``Ws``: step (or iteration) count and W at the checks made since the model
    last changed (a code that changes its model along the way, e.g. a stiffer K, starts a
    new list), oldest first. With s the newest step count, the look-back starts at the newest
    check made at or before (1 - lookback) s; W is settled when that check exists, at least
    ``window`` check intervals lie in the look-back, and every W in it is within
    w_tol * W_now of W_now. Scale-free: the look-back is a fraction of the run, whatever a
    step means to the code, so a slow drift is not mistaken for a plateau because the checks
    are close together. If W relaxes like exp(-t/tau), passing means |W - W_inf| < w_tol
    once the run is longer than ln 2 tau / lookback (2.1 tau).
    """
    if not steps:
        return False
    s = steps[-1]
    cut = (1.0 - lookback) * s
    first = None
    for k in range(len(steps)):
        if steps[k] <= cut:
            first = k
    if first is None or len(steps) - 1 - first < window:
        return False
    last = Ws[-1]
    return max(abs(w - last) for w in Ws[first:]) <= w_tol * abs(last)


def at_finish_line(figures, steps, Ws, overlap_tol=OVERLAP_TOL, w_tol=W_TOL, lookback=LOOKBACK,
                   window=W_WINDOW):
    """The finish line: max overlap <= overlap_tol at the newest check and W settled."""
    return figures["max_overlap"] <= overlap_tol and settled(steps, Ws, w_tol, lookback, window)


# ---- the work-precision frontier (frontier.py): one scoring for every recorded state ----------
FRONTIER_OVERLAP = 1e-3                                  # every level asks max overlap <= 1e-3 d
W_LEVELS = (1e-1, 3e-2, 1e-2, 3e-3, 1e-3, 3e-4)          # (W - W_best) / W_best <= level
KKT_LEVELS = (1e-1, 3e-2, 1e-2)                          # KKT residual <= level


def penalty_kkt_residual(x, diam, K):
    """The KKT residual of a soft-sphere (penalty) state, the penalty forces as multipliers:
    ||F|| / ||grad W|| with F_i = -(X_i - Xbar) + sum_j 2 K_kl (d_kl - r) u_ij (the net force
    of E = W + sum_{r < d_kl} K_kl (d_kl - r)^2, K_kl = K / d_kl^2, u_ij the unit vector from
    X_j to X_i) and grad W_i = X_i - Xbar. x (N, b), diam (N,) or a scalar; a float."""
    x = np.asarray(x, dtype=float)
    if x.ndim == 1:
        x = x[:, None]
    n = x.shape[0]
    diam = np.broadcast_to(np.asarray(diam, dtype=float), (n,))
    gw = x - x.mean(axis=0)
    F = -gw.copy()
    i, j = close_pairs(x, float(diam.max()))
    if i.size:
        v = x[i] - x[j]
        r = np.sqrt((v * v).sum(axis=1))
        dkl = 0.5 * (diam[i] + diam[j])
        mag = np.where(r < dkl, 2.0 * K / dkl ** 2 * (dkl - r), 0.0)
        fij = (mag / np.where(r > 0, r, 1.0))[:, None] * v      # on i, away from j
        np.add.at(F, i, fij)
        np.add.at(F, j, -fij)
    return net_force_residual(F, gw)


def net_force_residual(force, grad_w):
    """||F|| / ||grad W|| (F, grad W: (N, b)): 0 for no force and no pull, inf for a force
    without a pull."""
    gw_norm = math.sqrt(float((grad_w * grad_w).sum()))
    f_norm = math.sqrt(float((force * force).sum()))
    return f_norm / gw_norm if gw_norm > 0 else (0.0 if f_norm == 0 else math.inf)


def score_state(x, diam, K=None, kkt=None):
    """The frontier's figures of one recorded state, the same function for every code:
    max_overlap and W from the positions (``score``), and the KKT residual: from the
    positions with the penalty forces as multipliers when the code is a penalty code of
    stiffness ``K`` (LAMMPS), else ``kkt`` as the code reports it (mpipack's own residual of
    the same definition, ||grad W + sum lambda grad phi|| / ||grad W||), else NaN."""
    fig = score(x, diam)
    if K is not None:
        k = penalty_kkt_residual(x, diam, K)
    elif kkt is not None:
        k = float(kkt)
    else:
        k = math.nan
    return {"max_overlap": fig["max_overlap"], "W": fig["W"], "W_over_N2": fig["W_over_N2"],
            "density": fig["density"], "contacts_per_sphere": fig["contacts_per_sphere"], "kkt": k}


def best_w(traces, overlap_tol=FRONTIER_OVERLAP):
    """W_best: the lowest W over the states of all ``traces`` (lists of score_state dicts)
    with max overlap <= overlap_tol; None if there is none."""
    ws = [s["W"] for t in traces for s in t if s["max_overlap"] <= overlap_tol]
    return min(ws) if ws else None


def levels_reached(trace, W_best, overlap_tol=FRONTIER_OVERLAP, w_levels=W_LEVELS, kkt_levels=KKT_LEVELS):
    """For one code's trace (score_state dicts with "seconds", in time order): the first
    seconds at which each level holds, None where never. Keys "W<=level" (max overlap <=
    overlap_tol and (W - W_best) / W_best <= level) and "KKT<=level" (max overlap <=
    overlap_tol and kkt <= level; a NaN kkt never counts)."""
    out = {f"W<={lv:g}": None for lv in w_levels}
    out.update({f"KKT<={lv:g}": None for lv in kkt_levels})
    for s in trace:
        if not s["max_overlap"] <= overlap_tol:
            continue
        if W_best is not None:
            gap = (s["W"] - W_best) / W_best
            for lv in w_levels:
                if out[f"W<={lv:g}"] is None and gap <= lv:
                    out[f"W<={lv:g}"] = s["seconds"]
        for lv in kkt_levels:
            if out[f"KKT<={lv:g}"] is None and s["kkt"] <= lv:
                out[f"KKT<={lv:g}"] = s["seconds"]
    return out


def main(argv):
    for path in argv:
        d = np.load(path)
        print(json.dumps({"file": path, **score(d["x"], d["diam"])}))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
