"""Error measures recorded during a run (output.metrics_every -> metrics.csv): the paper's
N = 7 optimum is approached in every measure, and the rows are the same on 1, 2 and 3 ranks."""

import csv
from pathlib import Path

import numpy as np
import pytest

from conftest import describe
from support import CENTRE, no_walls

N7 = ["n=7", "init.sigma=1.0", "method.alpha=0.35", "method.beta=1.4", "method.gamma=0.7",
      "stop.rule=eps", "stop.eps=1e-8", "output.metrics_every=20", "output.w_optimum=3"]


def rows(run_mpipack, P, sets):
    proc, summary, _ = run_mpipack(P, None, sets)
    assert proc.returncode == 0, describe(proc)
    out = Path(proc.args[proc.args.index("--out") + 1])
    with open(out / "metrics.csv") as f:
        return summary, list(csv.DictReader(f))


def test_metrics_rows_approach_the_optimum_and_are_rank_independent(run_mpipack):
    runs = {P: rows(run_mpipack, P, N7) for P in (1, 2, 3)}
    summary, r1 = runs[1]
    its = [int(r["iteration"]) for r in r1]
    assert its[:3] == [20, 40, 60] and its[-1] == summary["iterations"]
    last = r1[-1]
    assert abs(float(last["W_minus_optimum"])) < 1e-9
    assert float(last["kkt_residual"]) < 1e-5 and float(last["max_overlap"]) < 1e-6
    assert float(last["A"]) < 1e-10 and int(last["active_pairs"]) == 12  # the hexagon and its centre
    first = r1[0]
    for col in ("max_overlap", "A", "kkt_residual"):
        assert float(last[col]) < 1e-3 * float(first[col]), col
    assert float(last["W"]) == summary["W"]
    for P in (2, 3):
        _, rp = runs[P]
        assert len(rp) == len(r1)
        for a, b in zip(r1, rp):
            for col in a:
                if col != "wall_seconds":
                    assert a[col] == b[col], (P, col, a[col], b[col])
    assert np.isfinite([float(r["wall_seconds"]) for r in r1]).all()


def _two_sphere_kkt(form, r, lam, pen, floor, tol):
    """The metrics pass on two spheres of diameter 1 at distance r on the x axis (Xbar = 0)
    with stored multiplier lam, in the force-multiplier mode: (KKT residual, pressure)."""
    from mpipack.parallel import exactsum
    from mpipack.kernels import daha as kernels
    x = np.array([[-r / 2, 0.0], [r / 2, 0.0]])
    diam = np.ones(2)
    po = np.array([0, 1, 2], dtype=np.int64)
    pj = np.array([1, 0], dtype=np.int64)
    pl = np.array([lam, lam])
    acc = exactsum.new_accumulator(kernels.N_MET_EXACT)
    mx = np.zeros(kernels.N_MET_MAX)
    pressure, contacts = np.zeros(2), np.zeros(2, dtype=np.int32)
    kernels.pair_metrics(form)(x, 2, diam, np.arange(2), po, pj, pl, *no_walls(2), np.zeros(2), CENTRE, 0.0,
                               kernels.LAMBDA_FORCE, 1.0, pen, floor, tol, False, acc, mx, pressure, contacts,
                               np.zeros(2), np.empty(0), np.empty(0))
    kkt2, gw2 = exactsum.value(acc, 0), exactsum.value(acc, 1)
    return float(np.sqrt(kkt2 / gw2)), pressure[0]


def test_the_certificate_uses_the_force_multipliers_of_pairs_in_contact():
    """Under fire-al the certificate's multipliers are mu = max(0, lambda + pen max(lambda,
    floor) phi / d^p), the forces the spheres move with, and a pair whose gap exceeds the
    tolerance carries none. Two spheres of diameter 1, S form: grad W at sphere 1 is r/2,
    grad phi is -2 r, so mu = 1/4 balances them exactly."""
    r = 0.9995  # overlapping by 5e-4 d: phi = 1 - r^2
    pen, floor = 4.0, 0.3
    stored = lambda r: 0.25 - pen * floor * (1.0 - r * r)  # below the floor: weight = floor
    kkt, mu = _two_sphere_kkt("S", r, stored(r), pen, floor, 1e-3)
    assert mu == pytest.approx(0.25, rel=1e-12) and kkt < 1e-12
    # the stored multiplier alone would not balance the pull
    assert abs(stored(r) - 0.25) / 0.25 > 1e-3
    # a pair 2e-3 d apart: no contact, no force, the residual is all of grad W
    kkt, mu = _two_sphere_kkt("S", 1.002, stored(1.002), pen, floor, 1e-3)
    assert mu == 0.0 and kkt == pytest.approx(1.0, rel=1e-12)
    # within the tolerance (a gap of 5e-4 d) it counts
    kkt, mu = _two_sphere_kkt("S", 1.0005, stored(1.0005), pen, floor, 1e-3)
    assert mu == pytest.approx(0.25, rel=1e-12) and kkt < 1e-12


@pytest.mark.parametrize("form", ["S", "NS"])
def test_force_imbalance_is_the_net_force_over_the_contact_forces(form):
    """Two spheres of diameter 1 at distance r on the x axis (Xbar = 0) whose multiplier
    carries half the force that balances the pull of W (r/2 at each sphere): the net force is
    r/4 and the contact force r/4, so the force imbalance is 1 and the KKT residual 1/2; with
    the balancing multiplier both are 0; with none the imbalance is infinite (no contact force)."""
    from mpipack.parallel import exactsum
    from mpipack.kernels import daha as kernels
    r = 0.999
    x = np.array([[-r / 2, 0.0], [r / 2, 0.0]])
    po, pj = np.array([0, 1, 2], dtype=np.int64), np.array([1, 0], dtype=np.int64)
    grad_phi = 2 * r if form == "S" else 1.0  # |grad phi| at distance r

    def figures(lam):
        acc = exactsum.new_accumulator(kernels.N_MET_EXACT)
        mx = np.zeros(kernels.N_MET_MAX)
        kernels.pair_metrics(form)(x, 2, np.ones(2), np.arange(2), po, pj, np.array([lam, lam]), *no_walls(2),
                                   np.zeros(2), CENTRE, 0.0, kernels.LAMBDA_STORED, 1.0, 0.0, 0.0, 1e-3, False,
                                   acc, mx, np.zeros(2), np.zeros(2, dtype=np.int32), np.zeros(2), np.empty(0),
                                   np.empty(0))
        kkt2, gw2, cf2 = (exactsum.value(acc, k) for k in (kernels.MET_KKT2, kernels.MET_GW2, kernels.MET_CF2))
        return np.sqrt(kkt2 / gw2), (np.sqrt(kkt2 / cf2) if cf2 > 0 else np.inf)

    balancing = (r / 2) / grad_phi
    kkt, imbalance = figures(balancing / 2)
    assert kkt == pytest.approx(0.5, rel=1e-12) and imbalance == pytest.approx(1.0, rel=1e-12)
    kkt, imbalance = figures(balancing)
    assert kkt < 1e-12 and imbalance < 1e-12
    kkt, imbalance = figures(0.0)
    assert kkt == pytest.approx(1.0, rel=1e-12) and imbalance == np.inf


@pytest.mark.parametrize("form", ["S", "NS"])
def test_net_force_per_sphere_is_its_row_of_the_kkt_residual(form):
    """Three spheres on the x axis (Xbar = 0): a touching pair at -r/2 and r/2 whose multiplier
    carries half the balancing force, and a free sphere at x = 3 with no partner. Net forces:
    r/4 on each of the pair (the pull r/2 less the contact force r/4), 3 on the free one (its
    whole pull). max_net_force is 3 and its share of the squared residual 9 / (9 + 2 (r/4)^2)."""
    from mpipack.parallel import exactsum
    from mpipack.kernels import daha as kernels
    r = 0.999
    x = np.array([[-r / 2, 0.0], [r / 2, 0.0], [3.0, 0.0]])
    po, pj = np.array([0, 1, 2, 2], dtype=np.int64), np.array([1, 0], dtype=np.int64)
    grad_phi = 2 * r if form == "S" else 1.0
    lam = 0.5 * (r / 2) / grad_phi
    acc = exactsum.new_accumulator(kernels.N_MET_EXACT)
    mx = np.zeros(kernels.N_MET_MAX)
    net = np.full(3, -1.0)
    kernels.pair_metrics(form)(x, 3, np.ones(3), np.arange(3), po, pj, np.array([lam, lam]), *no_walls(3),
                               np.zeros(2), CENTRE, 0.0, kernels.LAMBDA_STORED, 1.0, 0.0, 0.0, 1e-3, False,
                               acc, mx, np.zeros(3), np.zeros(3, dtype=np.int32), net, np.empty(0), np.empty(0))
    assert net == pytest.approx([r / 4, r / 4, 3.0], rel=1e-12)
    kkt2 = exactsum.value(acc, kernels.MET_KKT2)
    assert kkt2 == pytest.approx(9.0 + 2 * (r / 4) ** 2, rel=1e-12)
    assert mx[kernels.MET_NET] == pytest.approx(3.0, rel=1e-15)
