"""The L-BFGS inner solver's scalar side (``qn``, the two-loop recursion on a Gram matrix of
exact sums) and its per-sphere kernels (``kernels_qn``), against a plain L-BFGS on whole
vectors."""

import math

import numpy as np
import pytest

from mpipack.parallel import exactsum
from mpipack.kernels import lbfgs as kernels_qn
from mpipack.methods import lbfgs as qn


def quadratic(n, dim, seed):
    rng = np.random.default_rng(seed)
    a = rng.standard_normal((n * dim, n * dim))
    h = a @ a.T / (n * dim) + np.diag(rng.uniform(0.01, 3.0, n * dim))
    x_star = rng.standard_normal(n * dim)
    return h, x_star


def lbfgs_step(lb, x, g, mem):
    """One iteration through the kernels: the gradient g (as the fire-al gradient pass gives
    it, x_new = x - g), the dots, the scalar direction, the per-sphere update. Returns the
    next x and whether the step was accepted."""
    n, dim = x.shape
    k = qn.slots(lb.m)
    acc = exactsum.new_accumulator(k + 1 + dim + 2)
    head = lb.s["head"] if lb.s["stepped"] else -1
    x_next = x - g  # what the gradient pass leaves in x_new
    clipped = kernels_qn.dots(x, x_next, n, mem, head, 1e9, acc, np.zeros(1))
    values = exactsum.values_all(acc)
    coef, y_slot, s_slot, ok = lb.direction(values[:k + 1], values[k + 2 + dim], clipped > 0)
    if coef is None:
        kernels_qn.backtrack(x, x_next, n, mem, s_slot)
    else:
        kernels_qn.direction(x, x_next, n, mem, coef, y_slot, s_slot, 1e9)
    return x_next, ok


@pytest.mark.parametrize("m,dim,seed", [(5, 2, 0), (3, 3, 1), (1, 1, 2)])
def test_vector_free_two_loop_is_lbfgs(monkeypatch, m, dim, seed):
    """With every step accepted, the iterates are those of textbook L-BFGS (Nocedal and Wright,
    Algorithm 7.4, H0 = s.y / y.y) to rounding."""
    monkeypatch.setattr(qn, "ARMIJO", -math.inf)  # accept every step, as the reference does
    n = 40
    h, x_star = quadratic(n, dim, seed)
    grad = lambda v: h @ (v - x_star)
    lb = qn.LBFGS(m, h0=0.1)
    mem = np.zeros((n, qn.slots(m), dim))
    x = np.zeros((n, dim))
    xr, s_list, y_list, g_old, s_last, h0 = np.zeros(n * dim), [], [], None, None, 0.1
    worst = 0.0
    for it in range(40):
        x, ok = lbfgs_step(lb, x, grad(x.ravel()).reshape(n, dim), mem)
        assert ok or it == 0
        g = grad(xr)
        if g_old is not None:
            y = g - g_old
            s_list.append(s_last)
            y_list.append(y)
            h0 = (s_last @ y) / (y @ y)
            if len(s_list) > m:
                s_list.pop(0)
                y_list.pop(0)
        q, alphas = g.copy(), []
        for s_, y_ in zip(reversed(s_list), reversed(y_list)):
            a = (s_ @ q) / (y_ @ s_)
            q -= a * y_
            alphas.append(a)
        q *= h0
        for (s_, y_), a in zip(zip(s_list, y_list), reversed(alphas)):
            q += s_ * (a - (y_ @ q) / (y_ @ s_))
        s_last, g_old = -q, g
        xr = xr + s_last
        worst = max(worst, float(np.abs(x.ravel() - xr).max()) / (1.0 + float(np.abs(xr).max())))
        if np.linalg.norm(g) < 1e-9:
            break
    assert worst < 1e-9, worst
    assert np.linalg.norm(grad(x.ravel())) < 1e-6 * np.linalg.norm(grad(np.zeros(n * dim)))


def test_a_step_that_raises_the_function_is_halved():
    """A gradient step far too long for the curvature overshoots; it is undone by halves (the
    memory kept) until L falls, and then the iteration converges."""
    n, dim = 10, 2
    h, x_star = quadratic(n, dim, 3)
    f = lambda v: 0.5 * (v - x_star) @ h @ (v - x_star)
    grad = lambda v: h @ (v - x_star)
    lam_max = float(np.linalg.eigvalsh(h).max())
    lb = qn.LBFGS(5, h0=8.0 / lam_max)  # a gradient step 4 times the stable one
    mem = np.zeros((n, qn.slots(5), dim))
    x = np.zeros((n, dim))
    x1, ok = lbfgs_step(lb, x, grad(x.ravel()).reshape(n, dim), mem)
    assert f(x1.ravel()) > f(x.ravel())  # the first step overshot
    x2, ok = lbfgs_step(lb, x1, grad(x1.ravel()).reshape(n, dim), mem)
    assert not ok and lb.s["rejected"] == 1 and lb.s["backtracks"] == 1
    np.testing.assert_allclose(x2, 0.5 * (x + x1), rtol=0, atol=1e-14)  # half way, from x
    values = [f(x2.ravel())]
    x = x2
    f0 = f(np.zeros(n * dim))
    for _ in range(60):
        x, ok = lbfgs_step(lb, x, grad(x.ravel()).reshape(n, dim), mem)
        values.append(f(x.ravel()))
        if values[-1] < 1e-12 * f0:  # before rounding takes over
            break
    assert values[-1] < 1e-12 * f0
    assert lb.s["resets"] == 0  # backtracking sufficed: the memory was never dropped


def test_shortened_steps_drop_the_memory():
    n, dim = 8, 3
    h, x_star = quadratic(n, dim, 4)
    grad = lambda v: h @ (v - x_star)
    lb = qn.LBFGS(3, h0=0.2)
    k = qn.slots(3)
    mem = np.zeros((n, k, dim))
    x = np.zeros((n, dim))
    cap = 1e-3  # every sphere's first step is longer
    g = grad(x.ravel()).reshape(n, dim)
    acc = exactsum.new_accumulator(k + 1 + dim + 2)
    x1 = x - g
    kernels_qn.dots(x, x1, n, mem, -1, cap, acc, np.zeros(1))
    values = exactsum.values_all(acc)
    coef, y_slot, s_slot, _ = lb.direction(values[:k + 1], values[k + 2 + dim])
    kernels_qn.direction(x, x1, n, mem, coef, y_slot, s_slot, cap)
    np.testing.assert_allclose(np.linalg.norm(x1 - x, axis=1), cap, rtol=1e-12)
    g1 = grad(x1.ravel()).reshape(n, dim)
    acc = exactsum.new_accumulator(k + 1 + dim + 2)
    maxima = np.zeros(1)
    clipped = kernels_qn.dots(x1, x1 - g1, n, mem, lb.s["head"], cap, acc, maxima)
    assert clipped == n
    assert maxima[0] == pytest.approx(cap * cap, rel=1e-12)
    assert exactsum.values_all(acc)[k + 1 + dim] == pytest.approx(n * cap * cap, rel=1e-12)
    resets = lb.s["resets"]
    values = exactsum.values_all(acc)
    lb.direction(values[:k + 1], values[k + 2 + dim], clipped > 0)
    assert lb.s["resets"] == resets + 1 and lb.s["k"] == 0


def test_save_restore_continues_the_same():
    n, dim = 12, 2
    h, x_star = quadratic(n, dim, 5)
    grad = lambda v: h @ (v - x_star)
    lb = qn.LBFGS(4, h0=0.1)
    mem = np.zeros((n, qn.slots(4), dim))
    x = np.zeros((n, dim))
    for _ in range(7):
        x, _ = lbfgs_step(lb, x, grad(x.ravel()).reshape(n, dim), mem)
    import json
    twin = qn.LBFGS(4)
    twin.restore(json.loads(json.dumps(lb.save())))
    mem2, xa, xb = mem.copy(), x.copy(), x.copy()
    for _ in range(5):
        xa, _ = lbfgs_step(lb, xa, grad(xa.ravel()).reshape(n, dim), mem)
        xb, _ = lbfgs_step(twin, xb, grad(xb.ravel()).reshape(n, dim), mem2)
    assert np.array_equal(xa, xb)


def test_a_shortened_step_that_overshoots_halves_the_gradient_scale():
    """Two spheres pulled together (W's gradient) with a stiff wall where they meet: a
    gradient step of scale 1 is shortened by the trust region and lands deep in the wall; the
    next gradient (the wall's) is long too and throws it back. Untested, the pair repeated that
    2-cycle forever; tested with the step's slope where it began (an exact sum of ``dots``),
    each overshoot halves h0 (and bounds the s.y / y.y of later pairs, which away from the wall
    would be W's curvature, 1) until the steps fit the wall and the iterates settle at it."""
    n, dim, cap, wall, k_wall = 2, 3, 0.05, 1.0, 1500.0

    def grad(x):  # W = 1/2 sum |x_i - xbar|^2 plus a stiff penalty on |x_0 - x_1| < wall
        xbar = x.mean(axis=0)
        g = x - xbar
        r = x[0] - x[1]
        dist = np.linalg.norm(r)
        if dist < wall:
            push = -k_wall * (wall - dist) * r / dist
            g[0] += push
            g[1] -= push
        return g

    lb = qn.LBFGS(5, h0=1.0)
    k = qn.slots(5)
    mem = np.zeros((n, k, dim))
    x = np.array([[0.0, 0.0, -0.5015], [0.0, 0.0, 0.5015]])  # a gap of 3e-3
    gaps = []
    for _ in range(400):
        g = grad(x)
        acc = exactsum.new_accumulator(k + 1 + dim + 2)
        head = lb.s["head"] if lb.s["stepped"] else -1
        x_next = x - g
        clipped = kernels_qn.dots(x, x_next, n, mem, head, cap, acc, np.zeros(1))
        values = exactsum.values_all(acc)
        coef, y_slot, s_slot, _ = lb.direction(values[:k + 1], values[k + 2 + dim], clipped > 0)
        if coef is None:
            kernels_qn.backtrack(x, x_next, n, mem, s_slot)
        else:
            kernels_qn.direction(x, x_next, n, mem, coef, y_slot, s_slot, cap)
        x = x_next
        gaps.append(np.linalg.norm(x[0] - x[1]) - wall)
    assert lb.s["rejected"] > 0 and lb.s["h0_max"] < 0.1
    # settled where the wall balances the pull: k_wall (wall - dist) = 1/2 dist
    balance = -0.5 * wall / (k_wall + 0.5)
    assert max(abs(g - balance) for g in gaps[-50:]) < 1e-6


@pytest.mark.parametrize("dim", [1, 2, 3])
def test_unrolled_kernels_give_the_generic_bits(dim):
    """The kernels compiled for the run's number of slots (UNROLLED_SLOTS, the loops over the
    slots unrolled) leave the same bits as those for any number: the dots' accumulator, maxima
    and count, and the direction's memory and X^{n+1}, with the memory full and with some
    slots unused (coefficient 0). The run's memory is the unrolled one in every dimension."""
    k = kernels_qn.UNROLLED_SLOTS
    assert qn.slots(qn.MEMORY[dim]) == k
    rng = np.random.default_rng(40 + dim)
    n = 600  # more than two blocks of the exact sums' columns
    x = rng.normal(size=(n, dim)) * 10.0
    x_new = x - rng.normal(size=(n, dim)) * 1e-2
    mem = rng.normal(size=(n, k, dim)) * 1e-2
    cap = 0.02
    got = []
    for unrolled in (False, True):
        acc = exactsum.new_accumulator(k + 1 + dim + 2)
        maxima = np.zeros(1)
        count = kernels_qn._DOTS[dim, unrolled](x, x_new, n, mem, 3, cap, acc, maxima)
        got.append((acc, maxima, count))
    assert got[0][2] > 0 and np.array_equal(got[0][0], got[1][0]) and np.array_equal(got[0][1], got[1][1])
    assert got[0][2] == got[1][2]
    for coef in (rng.normal(size=k), np.where(np.arange(k) % 3 == 1, 0.0, rng.normal(size=k))):
        out = []
        for unrolled in (False, True):
            m2, xn = mem.copy(), x_new.copy()
            kernels_qn._DIRECTION[dim, unrolled](x, xn, n, m2, coef, 1, 2, cap)
            out.append((m2, xn))
        assert np.array_equal(out[0][0], out[1][0]) and np.array_equal(out[0][1], out[1][1])
        assert not np.array_equal(out[0][1], x_new)
