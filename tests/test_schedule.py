"""The fire-al schedule's decisions on synthetic reduced figures (no kernels, no MPI): when a
multiplier step is forced, when it is held back, and how far the penalty factor grows."""

import math

import pytest

from mpipack.methods import fire_al_schedule as schedule


def fire_schedule(overlap_tol=1e-3, dim=2):
    """An N = 2000 schedule whose start needs no explosion: phase "fire" after one figure."""
    sch = schedule.FireALSchedule(2000, dim, 1.0, "S", overlap_tol=overlap_tol)
    sch.observe(figure(sch, iteration=1, max_overlap=0.01))
    assert sch.phase == "fire"
    sch.take_pending()
    return sch


def figure(sch, iteration, max_overlap, residual=0.5):
    """Reduced figures of one iteration with inner residual ``residual`` (||grad L|| /
    ||grad W||) and positive power (no FIRE restart)."""
    w = sch.w_eq
    b = sch.s.b
    grad = residual * math.sqrt(2.0 * w)
    return {"iteration": iteration, "max_gain": 1.0, "max_row": 10.0 * b, "power": 1.0,
            "force2": (grad * b) ** 2, "change2": 1e-6, "W": w, "max_overlap": max_overlap}


def run_until_step(sch, first, max_overlap, limit, residual=0.5):
    """Iterations first, first + 1, ... until a multiplier step is taken; its iteration or None."""
    for it in range(first, first + limit):
        sch.coefficients()
        sch.observe(figure(sch, it, max_overlap, residual))
        if sch.s.dual_now:
            return it
    return None


def walk_to_lbfgs(sch, at_fire_step=None):
    """Forced multiplier steps (overlap 0.01) until the inner solves turn to L-BFGS. Returns
    (the iteration of the step that turned it on, the iteration after it, c_b after each step).
    ``at_fire_step(step)``, called after each step of FIRE's phase, may look at that step's
    pass and returns the iteration to go on from."""
    it, seen = 2, []
    while not sch.s.qn:
        step = run_until_step(sch, it, 0.01, schedule.FIRST_INNER + sch.fall_iterations + 10)
        assert step is not None and len(seen) < 12
        seen.append(sch.s.cb)
        it = step + 1
        if at_fire_step is not None and not sch.s.qn:
            it = at_fire_step(step)
    return step, it, seen


def test_the_first_forced_step_waits_for_the_fall_and_the_soft_phase():
    sch = fire_schedule()
    wait = schedule.FIRST_INNER + sch.fall_iterations
    step = run_until_step(sch, 2, 0.01, wait + 10)
    assert step is not None and step - 1 == wait, (step, wait)
    # the next one is forced MAX_INNER iterations later
    step2 = run_until_step(sch, step + 1, 0.01, schedule.MAX_INNER + 10)
    assert step2 - step == schedule.MAX_INNER, (step, step2)


def test_no_step_is_forced_while_the_overlap_is_within_the_hold():
    sch = fire_schedule(overlap_tol=1e-3)
    held = 0.9 * schedule.HOLD_OVERLAP * 1e-3
    wait = schedule.FIRST_INNER + sch.fall_iterations
    assert run_until_step(sch, 2, held, 3 * wait) is None
    # the same run with the overlap above the hold takes the forced step at once
    it = 2 + 3 * wait
    assert run_until_step(sch, it, 2.0 * schedule.HOLD_OVERLAP * 1e-3, 2) == it
    # the hold follows the stop's tolerance: at 1e-4 the same overlap is no longer held
    tight = fire_schedule(overlap_tol=1e-4)
    assert run_until_step(tight, 2, held, wait + 10) is not None


def test_a_converged_inner_solve_steps_whatever_the_overlap():
    sch = fire_schedule()
    run_until_step(sch, 2, 1e-5, schedule.MIN_INNER + 1, residual=0.1 * sch.s.eta)
    assert sch.s.dual_now and sch.s.dual_steps == 1


@pytest.mark.parametrize("dim", [2, 3])
def test_the_penalty_factor_grows_while_the_overlap_does_not_halve_up_to_its_cap(dim):
    """x2 from 4 in 2D, x8 from 16 in 3D (a glass: stiffer sooner); the continuous dual step
    (beta > 0 outside a multiplier step) runs only at the start's factor."""
    sch = fire_schedule(dim=dim)
    start, grow = {2: (4.0, 2.0), 3: (16.0, 8.0)}[dim]
    assert sch.coefficients().beta == schedule.OMEGA * start
    it = 2
    factors = []
    for _ in range(12):
        step = run_until_step(sch, it, 0.01, schedule.FIRST_INNER + sch.fall_iterations + 10)
        assert step is not None
        factors.append(sch.s.cb)
        it = step + 1
    assert factors[0] == start  # the first step has no step before it to compare with
    assert factors[1] == grow * start
    assert max(factors) == schedule.CB_MAX == 1024.0
    assert factors == sorted(factors)
    sch.coefficients()
    sch.observe(figure(sch, it, 0.01))  # the iteration after a step at a grown factor
    assert sch.coefficients().beta == 0.0


@pytest.mark.parametrize("dim", [2, 3])
def test_the_inner_solves_turn_to_lbfgs_once_the_penalty_is_stiff(dim):
    """L-BFGS from the multiplier step at which c_b reaches QN_FROM_CB: 256 in 2D (a crystal
    holds under it), the cap 1024 in 3D (a softer glass rearranges after every step)."""
    sch = fire_schedule(dim=dim)
    assert schedule.QN_FROM_CB[dim] == {2: 256.0, 3: 1024.0}[dim]
    step, it, seen = walk_to_lbfgs(sch)
    assert sch.s.cb == schedule.QN_FROM_CB[dim], seen
    assert all(cb < schedule.QN_FROM_CB[dim] for cb in seen[:-1]), seen
    assert sch.s.qn_from == step + 1
    assert sch.quasi_newton_pass() is False  # the multiplier step's pass comes first
    sch.coefficients()
    sch.observe(figure(sch, it, 0.01))
    assert sch.quasi_newton_pass()


@pytest.mark.parametrize("dim", [2, 3])
def test_the_lbfgs_phase_damps_its_multiplier_steps(dim):
    """In the L-BFGS phase a multiplier step is lambda <- max(0, lambda + QN_DUAL_STEP rho phi):
    its pass moves nothing (a3 = a4 = 0) and its dual gain is QN_DUAL_STEP c_b (half of it in
    2D, all of it in 3D); FIRE's phase keeps the full step (gain c_b)."""
    sch = fire_schedule(dim=dim)

    def full_step(step):  # a multiplier step of FIRE's phase: the full step
        a4, beta = sch.coefficients()[3:5]
        assert (a4, beta) == (0.0, sch.s.cb)  # the penalty off, lambda + c_b w phi
        sch.observe(figure(sch, step + 1, 0.01))
        return step + 2

    _, it, _ = walk_to_lbfgs(sch, at_fire_step=full_step)
    damp = {2: 0.5, 3: 1.0}[dim]
    assert schedule.QN_DUAL_STEP[dim] == damp
    cb = sch.s.cb
    a1, a2, a3, a4, beta = sch.coefficients()[:5]  # the multiplier step that turned L-BFGS on
    assert (a3, a4, beta) == (0.0, 0.0, damp * cb)
    sch.observe(figure(sch, it, 0.01))
    it += 1
    step = run_until_step(sch, it, 0.01, schedule.QN_MAX_INNER + 10)  # forced: overlap above tolerance
    assert step is not None and step - it <= schedule.QN_MAX_INNER
    a1, a2, a3, a4, beta = sch.coefficients()[:5]
    assert (a3, a4, beta) == (0.0, 0.0, damp * sch.s.cb)


def jammed_schedule(dim):
    """A schedule of stop.rule = "jammed" (``FireALSchedule(..., jammed=True)``), in phase fire."""
    sch = schedule.FireALSchedule(2000, dim, 1.0, "S", overlap_tol=1e-3, jammed=True)
    sch.observe(figure(sch, iteration=1, max_overlap=0.01))
    sch.take_pending()
    return sch


def test_a_jammed_3d_run_quenches_once_w_has_settled():
    """3D jammed: the first multiplier step as soon as W is the same at two window marks (not
    after the soft phase's FIRST_INNER beyond the fall), then one every QUENCH_MAX_INNER, and
    c_b grows at each though the overlap halves (the certified schedule would hold it)."""
    sch = jammed_schedule(3)
    assert sch.quench
    step = run_until_step(sch, 2, 0.01, schedule.FIRST_INNER)
    assert step == 1 + 2 * schedule.QUENCH_WINDOW, step  # the first mark at 101, equal at 201
    cbs = [sch.s.cb]
    for overlap in (2.5e-3, 1.2e-3, 5.5e-4):  # each under half the last, above the hold (5e-4)
        nxt = run_until_step(sch, step + 1, overlap, sch.quench_max_inner + 10)
        assert nxt is not None and nxt - step == sch.quench_max_inner == schedule.QUENCH_MAX_INNER, (step, nxt)
        step = nxt
        cbs.append(sch.s.cb)
    assert cbs == [schedule.C_B[3] * schedule.CB_GROW[3], schedule.CB_MAX, schedule.CB_MAX, schedule.CB_MAX]
    assert sch.s.qn  # the stiff phase's L-BFGS, its steps forced after QUENCH_MAX_INNER too


def test_a_jammed_3d_run_whose_w_still_falls_waits_for_the_soft_phase():
    """W falling by 1% per window never settles: the first step comes where the certified
    schedule's does."""
    sch = jammed_schedule(3)
    wait = schedule.FIRST_INNER + sch.fall_iterations
    for it in range(2, wait + 10):
        sch.coefficients()
        fig = figure(sch, it, 0.01)
        fig["W"] = sch.w_eq * (1.0 - 1e-4 * it)
        sch.observe(fig)
        if sch.s.dual_now:
            break
    assert it - 1 == wait, (it, wait)


def test_a_jammed_2d_run_quenches_from_a_smaller_ball():
    """2D jammed: spread to a ball of JAMMED_SPREAD law radii (2, not sqrt 6), a shorter fall;
    the first multiplier step once W has settled, then one every QUENCH_MAX_INNER, c_b doubling
    at each (2D's growth) though the overlap halves."""
    sch = jammed_schedule(2)
    certified = schedule.FireALSchedule(2000, 2, 1.0, "S", overlap_tol=1e-3)
    assert sch.quench and not certified.quench
    radius = certified.spread_radius / schedule.SPREAD  # the law's radius
    assert sch.spread_radius == pytest.approx(2.0 * radius) and schedule.SPREAD > 2.4
    assert sch.fall_iterations < 0.7 * certified.fall_iterations
    step = run_until_step(sch, 2, 0.01, schedule.FIRST_INNER)
    assert step == 1 + 2 * schedule.QUENCH_WINDOW, step
    cbs = [sch.s.cb]
    for overlap in (2.5e-3, 1.2e-3, 5.5e-4):
        nxt = run_until_step(sch, step + 1, overlap, sch.quench_max_inner + 10)
        assert nxt is not None and nxt - step == sch.quench_max_inner == schedule.QUENCH_MAX_INNER, (step, nxt)
        step = nxt
        cbs.append(sch.s.cb)
    assert cbs == [schedule.C_B[2] * schedule.CB_GROW[2] ** k for k in (1, 2, 3, 4)]


@pytest.mark.parametrize("n, dim, wait", [(2000, 2, 200), (20000, 2, 200), (100000, 2, 999), (200000, 2, 1999),
                                          (200000, 3, 200), (1000000, 3, 200)])
def test_a_large_2d_quench_waits_longer_between_its_multiplier_steps(n, dim, wait):
    """The quench's forced multiplier steps come every QUENCH_MAX_INNER (R / QUENCH_RADIUS)^2
    iterations beyond QUENCH_RADIUS (R the law's radius): 2D above N = 2e4; never in 3D up to
    N = 1e6 (R = 58 d). The schedule keeps to it, up to MAX_INNER in FIRE's phase."""
    sch = schedule.FireALSchedule(n, dim, 1.0, "S", overlap_tol=1e-3, jammed=True)
    radius = schedule.packing_law(n, dim, 1.0, "S")["radius"]
    assert sch.quench_max_inner == wait == int(schedule.QUENCH_MAX_INNER * max(1.0, radius / schedule.QUENCH_RADIUS) ** 2)
    sch.observe(figure(sch, iteration=1, max_overlap=0.01))
    sch.take_pending()
    step = run_until_step(sch, 2, 0.01, schedule.FIRST_INNER + sch.fall_iterations)
    assert step == 1 + 2 * schedule.QUENCH_WINDOW, step
    nxt = run_until_step(sch, step + 1, 2.5e-3, wait + 10)
    assert nxt is not None and nxt - step == min(wait, schedule.MAX_INNER), (step, nxt, wait)


def test_a_jammed_2d_start_between_the_two_balls_explodes_instead():
    """The spread ball must hold more W than the start: a start with W between that of the
    jammed ball (2 R) and the certified one (sqrt 6 R) is spread only by the certified schedule."""
    for jammed, spread in ((False, True), (True, False)):
        sch = schedule.FireALSchedule(2000, 2, 1.0, "S", overlap_tol=1e-3, jammed=jammed)
        fig = figure(sch, iteration=1, max_overlap=0.9)
        fig["W"] = 5.0 * sch.w_eq  # 2^2 = 4 < 5 < 6
        sch.observe(fig)
        assert sch.phase == "explode"
        assert (schedule.Request.EQUALISE in sch.take_pending()) == spread, jammed


def test_the_quench_mark_is_in_the_checkpoint():
    """A restart between two window marks compares W with the saved mark (bitwise restarts)."""
    sch = jammed_schedule(3)
    assert run_until_step(sch, 2, 0.01, 150) is None  # past the first mark (101)
    saved = sch.save()
    assert saved["w_mark"] == sch.w_eq
    again = schedule.FireALSchedule(2000, 3, 1.0, "S", overlap_tol=1e-3, jammed=True)
    again.restore(saved)
    assert run_until_step(again, 152, 0.01, 100) == 1 + 2 * schedule.QUENCH_WINDOW
