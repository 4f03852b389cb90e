"""Post-processing of packings: the measures of ``mpipack post`` as functions on arrays, and
the readers and commands behind the CLI (``source``, ``analysis``, ``commands``, ``export``).

On arrays (serial; rows in any order, results in the same order)::

    phi = mpipack.post.density_profile(x, diam, radii)     # phi(R) about the centre of mass
    n_i = mpipack.post.neighbour_counts(x, diam, 1.1)      # |X_i - X_j| < 1.1 d_ij
    psi = mpipack.post.hexatic(x, diam)                    # 2D: psi6_i (complex)
    q6, q6bar = mpipack.post.steinhardt_q6(x, diam)        # 3D: Q6_i, Qbar6_i
    r, g = mpipack.post.pair_distribution(x, diam, r_max)  # g(r) of the interior
    z = mpipack.post.contact_numbers(x, diam, gap=1e-3)    # Z, rattlers, Z - 2b

On files, on every rank of ``comm`` (each rank reads 1/P of the file)::

    a = mpipack.post.analyse("my-run")                     # the last snapshot of a run folder
    a.density().summary["plateau"], a.gr().summary["first_peak_g"]

The math of each measure: ``measures``. Importing this package imports numpy only.
"""

import numpy as np


def _local(x, diam, reach):
    from mpipack.parallel.comm import Comm
    from . import halo
    x = np.ascontiguousarray(x, dtype=np.float64)
    if x.ndim == 1:
        x = x[:, None]
    diam = np.ascontiguousarray(diam, dtype=np.float64)
    comm = Comm.serial()
    return comm, halo.distribute(comm, np.arange(len(x), dtype=np.int64), x, diam, reach)


def density_profile(x, diam, radii, centre=None):
    """phi(R) for each R of radii: the covered fraction of the ball B(centre, R) (default the
    centre of mass), from each sphere's exact intersection with it; shape (K,)."""
    from . import measures
    comm, local = _local(x, diam, 0.0)
    xbar = measures.centre_of_mass(comm, local, len(local.diam)) if centre is None else np.asarray(centre, float)
    return measures.density_profile(comm, local, xbar, radii)


def neighbour_counts(x, diam, factor=1.1):
    """n_i = #{j != i : |X_i - X_j| < factor d_ij}; shape (N,) int64."""
    from . import measures
    _, local = _local(x, diam, 0.0)
    i, _, _ = measures.close_pairs(local, factor, float(np.max(diam)))
    return np.bincount(i, minlength=len(local.diam))


def contact_numbers(x, diam, gap=1e-3):
    """Z (mean contacts, gap < gap d_ij), rattlers (removed until none has fewer than b + 1),
    Z without them and Z - 2b: a dict."""
    from . import measures
    comm, local = _local(x, diam, 0.0)
    i, j, _ = measures.close_pairs(local, 1.0 + gap, float(np.max(diam)))
    out, _ = measures.contact_summary(comm, local, i, j, local.x.shape[1], len(local.diam))
    return out


def hexatic(x, diam, factor=1.1):
    """2D: psi6_i = (1/n_i) sum_j exp(6 i theta_ij) over |X_i - X_j| < factor d_ij; complex (N,)."""
    from . import measures
    _, local = _local(x, diam, 0.0)
    i, j, _ = measures.close_pairs(local, factor, float(np.max(diam)))
    return measures.hexatic(local, i, j)


def steinhardt_q6(x, diam, factor=1.1):
    """3D: (Q6_i, Qbar6_i) over |X_i - X_j| < factor d_ij; two (N,) arrays."""
    from . import measures
    _, local = _local(x, diam, 0.0)
    i, j, _ = measures.close_pairs(local, factor, float(np.max(diam)))
    q, q6 = measures.steinhardt(local, i, j)
    return q6, measures.averaged_q(local, i, j, q)


def pair_distribution(x, diam, r_max, bins=200, r_bulk=None):
    """(r, g): g(r) at the bins' middles, centres the spheres within r_bulk - r_max of the centre
    of mass (r_bulk default: the outer end of the density plateau)."""
    from . import measures
    from .analysis import Analysis
    from .source import Packing
    x = np.ascontiguousarray(x, dtype=np.float64)
    x = x[:, None] if x.ndim == 1 else x
    n = len(x)
    pk = Packing(n=n, dim=x.shape[1], gid=np.arange(n, dtype=np.int64), x=x,
                 diam=np.ascontiguousarray(diam, dtype=np.float64), fields={}, pairs=None, iteration=0,
                 attrs={}, scene={}, path="", kind="arrays", summary={})
    from mpipack.parallel.comm import Comm
    a = Analysis(Comm.serial(), pk, r_max)
    if r_bulk is None:
        m = a.gr(r_max, bins)
        return m.table["r_over_d"] * a.d_mean, m.table["g"]
    edges = np.linspace(0.0, r_max, bins + 1)
    g, _, _, _ = measures.pair_distribution(a.comm, a.local, a.xbar, r_bulk, edges)
    return 0.5 * (edges[1:] + edges[:-1]), g


def analyse(path, comm=None, iteration=None, reach=None):
    """An ``analysis.Analysis`` of the snapshot ``iteration`` (None: the last) of a run folder, a
    snapshots.h5 or a checkpoint.h5, on ``comm`` (an mpi4py communicator; default serial).
    reach: the halo width (default 5 largest diameters, enough for every measure's defaults)."""
    from mpipack.parallel.comm import Comm
    from . import source
    from .analysis import Analysis
    c = Comm(comm) if comm is not None else Comm.serial()
    pk = source.read(c, path, iteration)
    d_max = float(c.allreduce(np.array([pk.diam.max() if len(pk.diam) else 0.0]), "max")[0])
    return Analysis(c, pk, 5.0 * d_max if reach is None else reach)


__all__ = ["density_profile", "neighbour_counts", "contact_numbers", "hexatic", "steinhardt_q6",
           "pair_distribution", "analyse"]
