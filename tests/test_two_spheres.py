"""Section 3 of the paper: two spheres in 1D under W = 1/(2N) sum |X_i - X_j|^2 (3.1).

For two free spheres, grad_{X_1} W = (X_1 - X_2)/2, so the KKT point (2.4) is |X_1 - X_2| = d
with lambda = d/2 for the non-smooth form (grad phi = -(X_1-X_2)/|X_1-X_2|) and lambda = 1/4
for the smooth form (grad phi = -2 (X_1 - X_2)), and W = d^2/4.

Runs in-process on one rank (comm.Comm() over MPI.COMM_WORLD of the pytest process).
"""

import numpy as np
import pytest

from conftest import step_each
from mpipack import config
from mpipack.engine import initial as init, solver
from mpipack.parallel.comm import Comm
from mpipack.engine import loop
from mpipack import errors

TOL = 1e-8


@pytest.fixture(scope="module")
def comm():
    c = Comm()
    assert c.size == 1
    return c


def run_two(comm, sets):
    scene = config.load("two-spheres", sets)
    s, res = loop.run(scene, comm)
    return scene, s, res, s.gather()


def assert_contact(g, res, d, lam_expected):
    assert g["x"].shape == (2, 1)
    dist = abs(g["x"][1, 0] - g["x"][0, 0])
    assert abs(dist - d) < TOL, (dist, d)
    assert g["pairs_gid"].tolist() == [[0, 1]], g["pairs_gid"]
    assert abs(g["pairs_lambda"][0] - lam_expected) < TOL, (g["pairs_lambda"], lam_expected)
    assert abs(res["W"] - d * d / 4) < 4 * TOL * d, (res["W"], d * d / 4)
    assert res["max_overlap"] < TOL
    assert res["active_pairs"] == 1


@pytest.mark.parametrize("d", [1.0, 2.0])
def test_daha_ns_two_spheres(comm, d):
    """Lemma 3.5 (Table 1 parameters alpha=0.3, beta=3, c=2): distance d, lambda = d/2."""
    scene, s, res, g = run_two(comm, [f"particles.diameter={d}"])
    assert scene.method.form == "NS" and scene.method.name == "daha"
    assert res["converged"], res
    assert res["iterations"] < 10000, res
    assert_contact(g, res, d, d / 2)
    # the centre of mass does not move: the forces on the two spheres are opposite
    x0 = init.positions(scene, np.arange(2, dtype=np.int64))
    assert abs(g["x"].mean() - x0.mean()) < 1e-12
    assert abs(x0[1, 0] - x0[0, 0]) < d, "test set-up: the spheres should start overlapping"


@pytest.mark.parametrize("d", [1.0, 2.0])
def test_daha_s_two_spheres(comm, d):
    """Lemma 3.6 (c > 2 alpha): distance d, lambda = 1/4. Section 4: for the smooth form beta
    scales as 1/d^2, so beta = 1.4/d^2 (with beta = 1.4 at d = 2 the discrete scheme's
    linearisation has an eigenvalue near -3: it does not converge, as expected)."""
    alpha, c = 0.35, 2.0
    beta = 1.4 / d ** 2
    assert c > 2 * alpha
    scene, s, res, g = run_two(comm, [f"particles.diameter={d}", "method.form=S",
                                      f"method.alpha={alpha}", f"method.beta={beta}",
                                      f"method.c={c}"])
    assert scene.method.gamma == pytest.approx(np.sqrt(alpha * beta), rel=1e-15)
    assert res["converged"], res
    assert_contact(g, res, d, 0.25)


def test_aha_ns_two_spheres_converges(comm):
    """Lemma 3.3: AHA-NS is asymptotically stable for any alpha, beta > 0."""
    d = 2.0
    _, s, res, g = run_two(comm, [f"particles.diameter={d}", "method.name=aha",
                                  "method.alpha=0.2", "method.beta=0.05"])
    assert res["converged"], res
    assert_contact(g, res, d, d / 2)


def trajectory(comm, sets, iters):
    """Distance, lambda and relative change after each of `iters` steps."""
    scene = config.load("two-spheres", sets + ["stop.eps=0", f"stop.max_iter={iters}"])
    s = solver.Solver(scene, comm)
    s.initialise()
    dist, lam, rel = np.empty(iters), np.empty(iters), np.empty(iters)

    def record(fig):
        it, st = fig["iteration"] - 1, s.state
        dist[it] = abs(st.x[1, 0] - st.x[0, 0])
        row = st.pair_lambda
        lam[it] = row.max() if row.size else 0.0
        rel[it] = fig["relative_change"]

    step_each(s, iters, record)
    return dist, lam, rel


def test_aha_s_two_spheres_keeps_circling_while_daha_s_converges(comm):
    """Lemma 3.4 / Fig. 2 ((alpha, beta, d) = (0.01, 0.01, 2)): AHA-S has a centre, and the
    iteration settles on a periodic orbit around (d, 1/4) instead of converging. DAHA-S with
    the same alpha and beta (gamma = sqrt(alpha beta), c = 2) spirals in."""
    d = 2.0
    base = [f"particles.diameter={d}", "method.form=S", "method.alpha=0.01", "method.beta=0.01"]
    iters = 30000
    dist, lam, rel = trajectory(comm, base + ["method.name=aha"], iters)
    late = slice(iters - 8000, iters)
    early = slice(4000, 12000)
    # not converging: distance and lambda keep swinging around the equilibrium (d, 1/4)
    assert dist[late].min() < d - 0.1 and dist[late].max() > d + 0.1, (dist[late].min(), dist[late].max())
    assert lam[late].min() < 0.25 - 0.1 and lam[late].max() > 0.25 + 0.1, (lam[late].min(), lam[late].max())
    assert rel[late].max() > 1e-3
    # and the swing does not decay (a periodic orbit, not a slow spiral)
    amp_early = dist[early].max() - dist[early].min()
    amp_late = dist[late].max() - dist[late].min()
    assert amp_late > 0.9 * amp_early, (amp_early, amp_late)

    ddist, dlam, drel = trajectory(comm, base + ["method.name=daha", "method.c=2"], iters)
    damp_early = ddist[early].max() - ddist[early].min()
    damp_late = ddist[late].max() - ddist[late].min()
    assert damp_late < 0.1 * damp_early, (damp_early, damp_late)
    assert damp_late < 0.01 * amp_late
    assert abs(ddist[-1] - d) < 1e-2 and abs(dlam[-1] - 0.25) < 1e-2
    assert drel[late].max() < 1e-5

    # with its own tuned beta = O(1/d^2), DAHA-S reaches the KKT point to 1e-8
    _, s, res, g = run_two(comm, [f"particles.diameter={d}", "method.form=S", "method.alpha=0.35",
                                  "method.beta=0.35"])
    assert res["converged"]
    assert_contact(g, res, d, 0.25)


def discrete_spectral_radius(alpha, beta, d):
    """Linearisation of the DAHA-S iteration (c = 2, gamma = sqrt(alpha beta)) for two free
    spheres about (R, lambda) = (d, 1/4), R = X_2 - X_1: with a3 = alpha^2/2, a4 = alpha beta/2,
        R' = R (1 - a3) + 4 lambda (a3 + a4 (d^2 - R^2)) R,  lambda' = lambda + beta (d^2 - R'^2)
    so y' = (1 - 2 a4 d^2) y + 4 a3 d mu and mu' = mu - 2 d beta y'."""
    a3, a4 = alpha ** 2 / 2, alpha * beta / 2
    p, q = 1 - 2 * a4 * d * d, 4 * a3 * d
    m = np.array([[p, q], [-2 * d * beta * p, 1 - 2 * d * beta * q]])
    return max(abs(np.linalg.eigvals(m)))


@pytest.mark.parametrize("alpha,beta,d", [(0.35, 1.4, 1.0), (0.35, 0.35, 2.0), (0.35, 1.4, 2.0),
                                          (0.1, 3.0, 1.0), (0.3, 6.0, 1.0)])
def test_daha_s_converges_iff_the_discrete_map_is_stable(comm, alpha, beta, d):
    """Lemma 3.6 is about the ODE; the iteration itself converges when its linearisation about
    the KKT point is a contraction. beta = 1.4 is fine for d = 1 but not for d = 2 (spectral
    radius ~3): section 4's advice beta = O(1/d^2) for the smooth form."""
    rho = discrete_spectral_radius(alpha, beta, d)
    assert abs(rho - 1) > 0.05, "test set-up: stay away from the stability boundary"
    sets = [f"particles.diameter={d}", "method.form=S", f"method.alpha={alpha}", f"method.beta={beta}",
            "stop.max_iter=5000"]
    if rho < 1:
        _, s, res, g = run_two(comm, sets)
        assert res["converged"], (rho, res)
        assert_contact(g, res, d, 0.25)
    else:
        # the watchdog stops the ringing contact (no progress, or growth) within the bound
        with pytest.raises(errors.NumericalError) as e:
            run_two(comm, sets)
        assert e.value.kind in ("stalled", "diverged") and e.value.solver.state.iteration < 5000
        # without it the run goes to its bound, not converged
        _, s, res, g = run_two(comm, sets + ["stop.watchdog=false"])
        assert not res["converged"], (rho, res)
        assert res["relative_change"] > 1e-6
