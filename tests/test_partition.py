"""The RCB partition's cuts (``parallel.domain.rcb``), on one process standing for P ranks:
each node's particles are split in the proportion of its ranks, exactly, with a fixed number
of allreduces per level of the tree. The partition on real ranks: tests/mpi_scripts/comm_checks.py."""

import numpy as np
import pytest

from mpipack.parallel import domain


class OneProcessComm:
    """P ranks whose particles all live in this process: a reduction is the local value."""

    def __init__(self, size):
        self.size = size
        self.allreduces = 0

    def allreduce(self, array, op="sum"):
        self.allreduces += 1
        return np.array(array, copy=True)


def shares(total, ranks):
    """What RCB gives each rank: a node of ``ranks`` ranks sends total * (ranks // 2) // ranks
    of its particles to its first half."""
    if ranks == 1:
        return [total]
    first = total * (ranks // 2) // ranks
    return shares(first, ranks // 2) + shares(total - first, ranks - ranks // 2)


@pytest.mark.parametrize("dim, P, n, seed", [(2, 2, 1001, 1), (2, 7, 5000, 2), (3, 3, 999, 3),
                                             (3, 16, 20000, 4), (1, 5, 777, 5), (2, 32, 300, 6)])
def test_every_rank_gets_its_exact_share(dim, P, n, seed):
    rng = np.random.default_rng(seed)
    x = rng.normal(0.0, 3.0, (n, dim)) * np.array([1.0, 0.5, 2.0][:dim])  # cuts near 0 too
    comm = OneProcessComm(P)
    part = domain.rcb(comm, x, n)
    owners = part.owners(x, n)
    assert np.bincount(owners, minlength=P).tolist() == shares(n, P)
    for r in range(P):  # every particle inside its own box: lo <= x < hi
        mine = x[owners == r]
        assert np.all(mine >= part.lo[r]) and np.all(mine < part.hi[r]), r
    levels = int(np.ceil(np.log2(P)))
    assert comm.allreduces == levels * (2 + domain._ROUNDS), comm.allreduces


def test_a_cut_is_the_float_just_above_its_target_coordinate():
    """Two ranks: the one cut is the smallest float above the n//2-th smallest coordinate on
    the longest axis, whatever the bracket it started from."""
    rng = np.random.default_rng(7)
    for scale in (1e-6, 1.0, 1e6):
        x = rng.uniform(-1.0, 3.0, (4001, 2)) * np.array([scale, 0.1 * scale])
        part = domain.rcb(OneProcessComm(2), x, len(x))
        target = len(x) * 1 // 2
        want = np.nextafter(np.sort(x[:, 0])[target - 1], np.inf)
        assert part.axis[0] == 0 and part.cut[0] == want, (scale, part.cut[0], want)


def test_coincident_coordinates_go_to_one_side():
    """A lattice has many equal coordinates: a cut never splits them, every rank's box still
    holds its particles, and no particle is lost."""
    g = np.arange(10, dtype=np.float64)
    x = np.stack(np.meshgrid(g, g, indexing="ij"), axis=-1).reshape(-1, 2)
    part = domain.rcb(OneProcessComm(4), x, len(x))
    owners = part.owners(x, len(x))
    counts = np.bincount(owners, minlength=4)
    assert counts.sum() == 100 and counts.min() > 0, counts
    for r in range(4):
        mine = x[owners == r]
        assert np.all(mine >= part.lo[r]) and np.all(mine < part.hi[r])


@pytest.mark.parametrize("P", [2, 3, 4])
def test_non_finite_coordinates_still_give_a_partition(P):
    """A diverging cloud (the run then stops with exit 3) may reach a rebuild with most
    coordinates NaN or infinite: the partition is still made, every finite particle owned."""
    rng = np.random.default_rng(P)
    x = rng.normal(0.0, 1.0, (400, 3))
    x[: 300, 0] = np.nan
    x[300: 350, 1] = np.inf
    part = domain.rcb(OneProcessComm(P), x, len(x))
    owners = part.owners(x, len(x))
    assert owners.shape == (400,) and np.all((owners[350:] >= 0) & (owners[350:] < P))
