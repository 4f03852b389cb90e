"""The certificate's multiplier fit (``fit``): the least KKT residual over multipliers >= 0 on
the pairs in contact, against an exact nonnegative least-squares solution by enumeration of
active sets (small clusters, one rank, in-process). Its rank-count independence is in
tests/test_parallel.py (a certified run whose KKT residual is the fit's, on 1, 2 and 3 ranks)."""

import itertools
import math

import numpy as np
import pytest

from mpipack import config
from mpipack.stop import measures
from mpipack.engine import solver
from mpipack.parallel.comm import Comm
from mpipack.parallel.state import BlockState


def solver_at(x, diam, form="S"):
    """A one-rank solver holding positions x (n, b) with lambda = 0 and every pair in its rows."""
    n, dim = x.shape
    scene = config.load("default", [f"n={n}", f"dim={dim}", f"method.form={form}", "method.alpha=0.01"])
    scene = scene.replace(neighbor={"skin": 100.0})  # every pair in the rows (beyond a scene's bound)
    s = solver.Solver(scene, Comm())
    empty = np.zeros(0)
    s.initialise(BlockState(n_global=n, dim=dim, gid_lo=0, x=x.copy(), x_prev=x.copy(),
                            diam=np.asarray(diam, float), hist_count=np.zeros(n, np.int64),
                            hist_gid=np.zeros(0, np.int64), hist_lambda=empty))
    return s


def exact_least_residual(x, diam, form, tol):
    """min over m >= 0 of ||(X - Xbar) + J^T m|| / ||X - Xbar||, the pairs within tol of contact,
    by trying every active set (the optimum is the least-squares solution on some set of pairs
    that is itself nonnegative)."""
    n, dim = x.shape
    g = (x - x.mean(axis=0)).ravel()
    cols = []
    for k, l in itertools.combinations(range(n), 2):
        dv = x[k] - x[l]
        r = np.linalg.norm(dv)
        dkl = 0.5 * (diam[k] + diam[l])
        if r > dkl * (1 + tol):
            continue
        col = np.zeros(n * dim)
        grad = -2.0 * dv if form == "S" else -dv / r
        col[k * dim:(k + 1) * dim] = grad
        col[l * dim:(l + 1) * dim] = -grad
        cols.append(col)
    best = np.linalg.norm(g)
    for size in range(1, len(cols) + 1):
        for subset in itertools.combinations(range(len(cols)), size):
            A = np.stack([cols[c] for c in subset], axis=1)
            m, *_ = np.linalg.lstsq(A, -g, rcond=None)
            if (m >= -1e-12).all():
                best = min(best, np.linalg.norm(g + A @ np.maximum(m, 0)))
    return best / np.linalg.norm(g), len(cols)


def test_a_packed_triangle_is_balanced_by_the_fit():
    """Three touching discs: stationary, but the run's multipliers (zero) say KKT = 1."""
    x = np.array([[0.0, 0.0], [1.0, 0.0], [0.5, np.sqrt(0.75)]])
    s = solver_at(x, [1.0, 1.0, 1.0])
    fig, _ = measures.measure(s, overlap_a=False)
    assert fig["kkt_residual"] == pytest.approx(1.0)
    kkt, steps = measures.best_kkt(s, fig, target=1e-9)
    assert kkt <= 1e-9 and steps > 0


def test_an_unsupported_sphere_is_not_balanced():
    """An L of three discs: the outer two are pulled sideways off their single contact, which
    no nonnegative multiplier can hold (the exact least residual is 0.5)."""
    x = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    s = solver_at(x, [1.0, 1.0, 1.0])
    fig, _ = measures.measure(s, overlap_a=False)
    kkt, _ = measures.best_kkt(s, fig, target=1e-2)
    exact, pairs = exact_least_residual(x, [1.0] * 3, "S", s.scene.stop.overlap)
    assert pairs == 2 and exact == pytest.approx(0.5)
    assert exact - 1e-12 <= kkt <= exact + 1e-6


@pytest.mark.parametrize("form", ["S", "NS"])
@pytest.mark.parametrize("dim,seed", [(1, 0), (1, 1), (2, 0), (2, 1), (2, 2), (2, 3), (3, 0), (3, 1), (3, 2)])
def test_the_fit_reaches_the_least_residual(form, dim, seed):
    """Random clusters of 6 overlapping spheres of mixed sizes, in 1, 2 and 3 dimensions (each
    its own compiled kernels): the fit's residual is never below the exact minimum (it is an
    actual m >= 0's) and reaches it."""
    rng = np.random.default_rng(seed)
    diam = rng.uniform(1.0, 1.5, 6)
    x = rng.normal(scale=0.7, size=(6, dim))
    s = solver_at(x, diam, form)
    fig, _ = measures.measure(s, overlap_a=False)
    kkt, _ = measures.best_kkt(s, fig, target=0.0)
    exact, pairs = exact_least_residual(x, diam, form, s.scene.stop.overlap)
    assert pairs >= 4, "test set-up: want several contacts"
    assert exact - 1e-8 <= kkt <= exact + 1e-5, (kkt, exact)


def test_no_contact_leaves_the_pull_of_w():
    x = np.array([[0.0, 0.0], [3.0, 0.0]])
    s = solver_at(x, [1.0, 1.0])
    fig, _ = measures.measure(s, overlap_a=False)
    assert measures.best_kkt(s, fig, target=1e-2) == (1.0, 0)


def test_the_fit_takes_no_more_steps_than_allowed():
    """The certifier gives a fit the budget left (``max_steps``); the fit keeps to it and its
    residual is that of an actual m >= 0 (never below the exact minimum)."""
    rng = np.random.default_rng(1)
    diam = rng.uniform(1.0, 1.5, 6)
    x = rng.normal(scale=0.7, size=(6, 3))
    s = solver_at(x, diam)
    fig, _ = measures.measure(s, overlap_a=False)
    exact, _ = exact_least_residual(x, diam, "S", s.scene.stop.overlap)
    for cap in (1, 7, 40):
        kkt, steps = measures.best_kkt(s, fig, target=0.0, max_steps=cap)
        assert steps == cap and kkt >= exact - 1e-8


def test_the_momentum_beats_plain_projected_gradient_steps(monkeypatch):
    """A heap of 200 overlapping discs (a few hundred contacts): with FISTA's momentum the fit
    gets further in 200 steps than the same steps with the momentum off (beta = 0
    throughout; measured 1.3e-4 against 0.28)."""
    from mpipack.stop import fit
    rng = np.random.default_rng(0)
    n = 200
    x = rng.uniform(-6.0, 6.0, size=(n, 2))
    for _ in range(400):  # push overlapping pairs apart and pull all to the centre: a heap
        dv = x[:, None, :] - x[None, :, :]
        r = np.linalg.norm(dv, axis=2) + np.eye(n)
        push = np.clip(1.0 - r, 0.0, None) * (1 - np.eye(n))
        x += 0.3 * (push[:, :, None] * dv / r[:, :, None]).sum(1) - 0.01 * (x - x.mean(0))
    s = solver_at(x, np.ones(n))
    fig, _ = measures.measure(s, overlap_a=False)
    with_momentum, steps = measures.best_kkt(s, fig, target=0.0, max_steps=200)
    assert steps == 200

    plain_step = kernels_fit_step_without_momentum(fit)
    monkeypatch.setattr(fit.kernels_fit, "fit_kernels", plain_step)
    plain, _ = measures.best_kkt(s, fig, target=0.0, max_steps=200)
    assert with_momentum < 0.8 * plain, (with_momentum, plain)


def kernels_fit_step_without_momentum(fit):
    """fit_kernels whose step ignores beta (plain projected gradient steps)."""
    original = fit.kernels_fit.fit_kernels

    def kernels(form):
        start, step, gradient = original(form)

        def plain(x, n_local, co, cj, m, m_prev, g, wa, diam, wm, wm_prev, wg, wact, xbar, pot, length, beta, r, acc):
            step(x, n_local, co, cj, m, m_prev, g, wa, diam, wm, wm_prev, wg, wact, xbar, pot, length, 0.0, r, acc)
        return start, plain, gradient
    return kernels


def test_the_certifier_gives_the_first_fit_less_budget_than_later_ones(monkeypatch):
    """The fits' budget is a fifth of the run's iterations less the steps spent: the first fit
    of a run needs FIRST_FIT_STEPS of it (250: short runs are certified by a fit), every later
    one MIN_FIT_STEPS (500: 250-step fits left 3D N = 1e5 uncertified); each takes the budget
    left. Checked with a stand-in for the metrics pass and for a fit that never certifies."""
    from mpipack.stop import certificate as certify
    from mpipack.config import Stop
    stop = Stop(rule="certified", eps=0.0, max_iter=100000, max_seconds=math.inf, overlap=1e-3,
                kkt=1e-2, w_rtol=1e-4, w_window=0.1, check_every=50, watchdog=True)
    fits = []
    monkeypatch.setattr(measures, "measure", lambda s, **kw: (
        {"kkt_residual": 0.05, "max_overlap": 0.0, "W": 1.0}, None))
    monkeypatch.setattr(measures, "best_kkt", lambda s, m, target, max_steps: (
        fits.append(max_steps) or 0.05, max_steps))
    cert = certify.Certifier(stop)
    recorded = [0]

    def check(iteration):
        for i in range(recorded[0], iteration):
            cert.record(i, 1.0)  # W settled
        recorded[0] = iteration
        return cert.check(None, {"iteration": iteration, "W": 1.0, "max_overlap": 0.0})

    assert certify.FIRST_FIT_STEPS < certify.MIN_FIT_STEPS

    def budget(now, spent):  # fit steps left: a FIT_SHARE of the iterations, at FIT_STEP_COST
        return int((certify.FIT_SHARE * now - certify.FIT_STEP_COST * spent) / certify.FIT_STEP_COST)

    def first_check(since, spent, least):  # the first check (every 50) with `least` steps left
        it = since + 50
        while budget(it, spent) < least:
            it += 50
        return it

    first = first_check(0, 0, certify.FIRST_FIT_STEPS)
    assert not check(first - 50) and fits == []  # less than 250 steps of budget: no fit yet
    assert not check(first) and fits == [budget(first, 0)]  # the first fit takes the budget
    spent = fits[0]
    # later fits wait for MIN_FIT_STEPS of budget, not FIRST_FIT_STEPS
    later = first_check(first, spent, certify.MIN_FIT_STEPS)
    assert budget(later - 50, spent) >= certify.FIRST_FIT_STEPS
    assert not check(later - 50) and len(fits) == 1
    assert not check(later) and fits[1] == budget(later, spent) >= certify.MIN_FIT_STEPS
    assert cert.fit_steps == fits[0] + fits[1]
