"""Helpers shared by the test modules (none imports another test module): the independent
references the tests check the package against, written from the paper's formulas in plain
numpy. The environment and launch of mpirun subprocesses are in conftest.py."""

import math

import numpy as np


def ref_phi_grad(form, xk, xl, dkl):
    """phi_kl and grad_{X_k} phi_kl (grad_{X_l} phi_kl is its negative), Definition 2.1."""
    diff = xk - xl
    r2 = float(np.dot(diff, diff))
    if form == "S":
        return dkl * dkl - r2, -2.0 * diff
    r = math.sqrt(r2)
    return dkl - r, -diff / r


def random_cloud(rng, n, dim, polydisperse=True):
    """Overlapping random spheres: a dense Gaussian cloud."""
    x = rng.normal(size=(n, dim)) * (0.35 * n ** (1.0 / dim))
    diam = rng.uniform(0.8, 1.3, size=n) if polydisperse else np.ones(n)
    return x, diam


def random_lambda(rng, form, x, diam, frac=0.8):
    """Symmetric lambda^{n-1}: random positive values on a random part of the overlapping pairs."""
    n = x.shape[0]
    lam = np.zeros((n, n))
    for k in range(n):
        for l in range(k + 1, n):
            phi, _ = ref_phi_grad(form, x[k], x[l], 0.5 * (diam[k] + diam[l]))
            if phi > 0 and rng.uniform() < frac:
                lam[k, l] = lam[l, k] = rng.uniform(0.05, 1.0) * (0.5 if form == "S" else 1.0)
    return lam


def rows_complete(n_local, n_total, gid):
    """Pair rows with every other particle as partner, sorted by partner gid."""
    offsets = np.zeros(n_local + 1, np.int64)
    js = []
    for i in range(n_local):
        partners = [j for j in range(n_total) if j != i]
        partners.sort(key=lambda j: gid[j])
        js.extend(partners)
        offsets[i + 1] = len(js)
    return offsets, np.array(js, dtype=np.int32)


def brute_force_figures(d):
    """W (3.1), largest relative overlap (d_ij - r)/d_ij and lambda > 0 pair count from a dump."""
    x, diam = d["x"], d["diam"]
    n = x.shape[0]
    w = 0.0
    for i in range(n):  # W = 1/(2N) sum_{i<j} |X_i - X_j|^2, row by row to bound memory
        w += float(((x[i + 1:] - x[i]) ** 2).sum())
    w /= 2 * n
    r = np.sqrt(((x[:, None, :] - x[None, :, :]) ** 2).sum(axis=2))
    dij = 0.5 * (diam[:, None] + diam[None, :])
    ov = (dij - r) / dij
    np.fill_diagonal(ov, -np.inf)
    return w, max(float(ov.max()), 0.0)


# the kernels' potential argument for the paper's W (``kernels.potential``: no gravity)
CENTRE = np.zeros(4)


def no_walls(n_local):
    """The walls arguments of a kernel without a container (``kernels.walls``): no wall, and
    n_local spheres with no wall multiplier."""
    return np.zeros((0, 8)), np.zeros((n_local, 0))
