"""Post-processing of gathered configurations (serial): packing density phi(R) about the centre
of mass (paper, Figs. 8 and 10a) and neighbour counts (Fig. 10b)."""

import numpy as np


def density_profile(x, diam, radii):
    """phi(R): covered fraction of the ball B(Xbar, R) for each R (serial, gathered data)."""
    from mpipack.parallel import exactsum
    from mpipack.kernels import metrics
    xbar = x.mean(axis=0)
    acc = exactsum.new_accumulator(len(radii))
    metrics.covered_measure(np.ascontiguousarray(x), diam, x.shape[0], xbar, np.asarray(radii, float), acc)
    return np.array([exactsum.value(acc, q) / metrics.ball_measure(x.shape[1], R) for q, R in enumerate(radii)])


def neighbour_counts(x, diam, factor=1.1):
    """Number of neighbours of each sphere with centre distance < factor * d_ij."""
    from mpipack.parallel import neighbors
    n = x.shape[0]
    x = np.ascontiguousarray(x)
    off, pj, _, _ = neighbors.build_rows(x, n, n, np.arange(n, dtype=np.int64), diam,
                                         (factor - 1.0) * float(diam.max()), np.zeros(n + 1, np.int64),
                                         np.empty(0, np.int64), np.empty(0))
    counts = np.zeros(n, dtype=np.int64)
    for i in range(n):
        js = pj[off[i]:off[i + 1]]
        r = np.sqrt(((x[js] - x[i]) ** 2).sum(axis=1))
        counts[i] = int(np.sum(r < factor * 0.5 * (diam[i] + diam[js])))
    return counts
