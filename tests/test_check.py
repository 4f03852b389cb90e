"""``mpipack check``: the two-sphere stability conditions (ODE and scheme), the verdict against
real runs just inside and just outside the stable region, the start's overlap estimate against
a generated start, memory refusals, and the command line's exit codes."""

import csv
import math
import subprocess
import sys

import numpy as np
import pytest

from conftest import describe, mpi_env, mpirun

from mpipack.analysis import check, footprint, stability
from mpipack import config


def cli(args, cwd, timeout=300):
    return subprocess.run([sys.executable, "-m", "mpipack.cli"] + [str(a) for a in args], cwd=str(cwd),
                          env=mpi_env(), capture_output=True, text=True, timeout=timeout)


def two(form, **method):
    sets = [f'method.form="{form}"'] + [f"method.{k}={v!r}" if not isinstance(v, str) else f'method.{k}="{v}"'
                                         for k, v in method.items()]
    return config.load("two-spheres", sets)


# ---- the two-sphere analysis --------------------------------------------------------------------
def test_ode_of_two_free_spheres_daha_s_needs_c_above_4_alpha():
    """s^3 + c s^2 + 2 gamma^2 d^2 s + 8 alpha^2 beta d^2 with gamma^2 = alpha beta: the largest
    real part crosses 0 at c = 4 alpha (the paper's one fixed sphere: c = 2 alpha)."""
    alpha, beta = 0.3, 2.0
    gamma = math.sqrt(alpha * beta)
    for c, stable in ((4 * alpha * 0.99, False), (4 * alpha * 1.01, True)):
        s = np.roots(stability.ode_polynomial("daha", "S", alpha, beta, gamma, c))
        assert (s.real.max() < 0) == stable, (c, s)
        assert stability.ode_condition("daha", "S", alpha, beta, gamma, c)[3] == stable
    for c, stable in ((2 * alpha * 0.99, False), (2 * alpha * 1.01, True)):
        s = np.roots(stability.ode_polynomial("daha", "S", alpha, beta, gamma, c, fixed_sphere=True))
        assert (s.real.max() < 0) == stable


def test_ode_of_two_free_spheres_ns_and_aha():
    a, b, c = 0.3, 3.0, 2.0
    g = math.sqrt(a * b)
    # DAHA-NS: c (alpha^2 + gamma^2 d) > 2 alpha^2 beta, Routh-Hurwitz of the cubic
    coef = stability.ode_polynomial("daha", "NS", a, b, g, c)
    assert coef == [1.0, c, a * a + g * g, 2 * a * a * b]
    # AHA-S: a centre (purely imaginary roots) for any alpha, beta; AHA-NS always stable
    s = np.roots(stability.ode_polynomial("aha", "S", 0.01, 0.01, 0.0, 0.0))
    assert np.allclose(s.real, 0.0)
    s = np.roots(stability.ode_polynomial("aha", "NS", a, b, 0.0, 0.0))
    assert s.real.max() < 0


def reference_map(method, form, alpha, beta, gamma, c, d=1.0):
    """(2.10) as the kernel runs it, for two spheres in 1D, on the state (r^n, r^{n-1},
    lambda^{n-1}): lambda^n = max(0, lambda^{n-1} + beta phi(r^n)), then r^{n+1}. Written from
    the paper's equations, independently of check's algebra."""
    if method == "daha":
        h = 1 + c / 2
        a1, a2, a3, a4 = 2 / h, -(1 - c / 2) / h, alpha ** 2 / h, gamma ** 2 / h
    else:
        a1, a2, a3, a4 = 1.0, 0.0, alpha, 0.0

    def step(s):
        r, rp, lam = s
        phi = d * d - r * r if form == "S" else d - abs(r)
        lam = max(0.0, lam + beta * phi)
        gdiff = -4 * r if form == "S" else -2 * np.sign(r)  # grad_1 phi - grad_2 phi
        # X_1 and X_2 move by +-: r^{n+1} = a1 r + a2 r_prev - a3 r - lambda (a3 + a4 phi) gdiff
        rn = a1 * r + a2 * rp - a3 * r - lam * (a3 + a4 * phi) * gdiff
        return np.array([rn, r, lam])
    return step


@pytest.mark.parametrize("method,form,params", [
    ("daha", "S", (0.35, 1.4, math.sqrt(0.49), 2.0)),
    ("daha", "S", (7.8e-3, 2.8e3, 1.6e-2, 2.0)),
    ("daha", "NS", (0.3, 3.0, math.sqrt(0.9), 2.0)),
    ("daha", "NS", (0.3, 3.0, 0.5, 0.7)),
    ("daha", "S", (0.2, 1.0, 0.4, 3.5)),
    ("aha", "NS", (0.3, 3.0, 0.0, 0.0)),
    ("aha", "S", (0.01, 0.01, 0.0, 0.0)),
])
def test_discrete_eigenvalues_match_the_scheme(method, form, params):
    """The cubic P(z) = z^3 + (q + K - 2 - m) z^2 + (1 + 2m - K) z - m has the eigenvalues of the
    scheme's Jacobian at its fixed point (finite differences of a direct implementation)."""
    alpha, beta, gamma, c = params
    step = reference_map(method, form, alpha, beta, gamma, c)
    lam = 0.25 if form == "S" else 0.5
    fix = np.array([1.0, 1.0, lam])
    assert np.allclose(step(fix), fix, atol=1e-12)
    h = 1e-7
    Jac = np.column_stack([(step(fix + h * e) - step(fix - h * e)) / (2 * h) for e in np.eye(3)])
    want = np.sort(np.abs(np.linalg.eigvals(Jac)))
    K, q, m = stability.contact_gains(method, form, alpha, beta, gamma, c)
    got = np.sort(np.abs(stability.cubic_roots(K, q, m)))  # AHA: one-step, the r^{n-1} slot is z = 0
    assert np.allclose(want, got, atol=1e-6), (want, got)
    # and the cluster code on two spheres is the same map
    P = stability.cluster(2, 1, form)
    assert abs(stability.cluster_radius(P, method, alpha, beta, gamma, c) - want.max()) < 1e-6


def test_ode_and_scheme_disagree_at_large_steps():
    # the paper's N = 2000 parameters: the ODE is unstable, the scheme stable (rate K/2)
    sc = config.load("paper-2d", ["n=2"])
    t = stability.two_spheres(sc)
    assert not t["ode_ok"] and t["ok"]
    assert abs(t["rho"] - math.sqrt(1 - t["K"])) < 1e-12
    # alpha = 0.35, beta = 4: the ODE stable (c > 4 alpha), the scheme not (2K + q > 4)
    t = stability.two_spheres(two("S", alpha=0.35, beta=4.0))
    assert t["ode_ok"] and not t["ok"]


def test_seven_discs_cluster_matches_the_measured_buckling_edge():
    """7 DAHA-S discs, alpha = 0.04, beta = 0.15: runs certify at gamma = 0.045 and not at 0.04
    (alpha/gamma = 0.89 and 1.0); the cluster's scheme crosses 1 between them."""
    P = stability.cluster(7, 2, "S")
    assert P["contacts"] == 12 and P["residual"] < 1e-12
    assert stability.cluster_radius(P, "daha", 0.04, 0.15, 0.045, 2.0) < 1.0
    assert stability.cluster_radius(P, "daha", 0.04, 0.15, 0.040, 2.0) > 1.0


# ---- against real runs --------------------------------------------------------------------------
def beta_edge(scene):
    return check._edge(lambda b: stability.verdict(stability.with_param(scene, "beta", b))[0], scene.method.beta, 2.0,
                       bisect=40)


@pytest.mark.parametrize("method,form,alpha,beta0,edge", [
    ("daha", "S", 0.35, 1.4, 4 / (0.49 + 0.7)),            # c = 2: 2K + q < 4, gamma^2 = alpha beta
    ("daha", "NS", 0.3, 3.0, (4 - 0.09) / (0.3 + 0.09)),    # alpha^2 + alpha beta + alpha^2 beta < 4
    ("aha", "NS", 0.3, 3.0, 2 / 0.3 - 1),                   # alpha (1 + beta) < 2
])
def test_two_sphere_verdict_against_runs(tmp_path, method, form, alpha, beta0, edge):
    """Just inside the stable region the run certifies; just outside it the watchdog stops it
    (exit 3, as the check's verdict): the contact rings or grows instead of settling."""
    sc = two(form, name=method, alpha=alpha, beta=beta0)
    b = beta_edge(sc)
    assert abs(b - edge) < 1e-6 * edge, (b, edge)
    for factor, want in ((0.96, 0), (1.04, 3)):
        sets = [f'method.name="{method}"', f'method.form="{form}"', f"method.alpha={alpha}",
                f"method.beta={factor * b!r}", 'stop.rule="certified"', "stop.max_iter=4000",
                "output.snapshots=false"]
        proc = cli(["check", "two-spheres"] + sum((["--set", s] for s in sets), []), tmp_path)
        assert proc.returncode == want, describe(proc)
        out = tmp_path / f"run-{method}-{form}-{factor}"
        proc = mpirun(1, [sys.executable, "-m", "mpipack.cli", "run", "two-spheres", "--quiet", "--out", out]
                      + sum((["--set", s] for s in sets), []), cwd=tmp_path)
        assert proc.returncode == want, (factor, describe(proc))


def test_aha_s_two_spheres_never_converge(tmp_path):
    proc = cli(["check", "two-spheres", "--set", 'method.name="aha"', "--set", 'method.form="S"',
                "--set", "method.alpha=0.01", "--set", "method.beta=0.01"], tmp_path)
    assert proc.returncode == 3, describe(proc)
    assert "spectral radius 1.000000" in proc.stdout


def test_decay_rate_of_a_run_is_the_spectral_radius(tmp_path):
    """DAHA-S alpha = 0.1, beta = 1: |z| = sqrt(1 - K) = 0.9487 per iteration; a real run's
    relative change decays at that rate."""
    sets = ['method.form="S"', "method.alpha=0.1", "method.beta=1.0", 'stop.rule="eps"', "stop.eps=0",
            "stop.max_iter=400", "output.metrics_every=1", "output.snapshots=false"]
    rho = stability.two_spheres(config.load("two-spheres", sets))["rho"]
    assert abs(rho - math.sqrt(0.9)) < 1e-12
    proc = mpirun(1, [sys.executable, "-m", "mpipack.cli", "run", "two-spheres", "--quiet", "--out", tmp_path / "o"]
                  + sum((["--set", s] for s in sets), []), cwd=tmp_path)
    assert proc.returncode == 0, describe(proc)
    with open(tmp_path / "o" / "metrics.csv") as f:
        pts = [(int(r["iteration"]), float(r["relative_change"])) for r in csv.DictReader(f)]
    pts = [(i, v) for i, v in pts if 1e-11 < v < 1e-4]
    assert len(pts) > 100
    slope = np.polyfit([i for i, _ in pts], np.log([v for _, v in pts]), 1)[0]
    assert abs(slope / math.log(rho) - 1) < 0.1, (slope, math.log(rho))


# ---- the start and the memory ------------------------------------------------------------------
@pytest.mark.parametrize("sets", [
    ["n=2000", "dim=2", "init.sigma=1.0"],
    ["n=1500", "dim=3", "init.sigma=1.5"],
    ["n=800", "dim=1", "init.sigma=30.0"],
    ["n=600", "dim=2", 'init.kind="lattice"', "init.spacing=0.5"],
])
def test_overlap_estimate_against_a_generated_start(sets):
    from mpipack.engine import initial as init
    sc = config.load(None, sets)
    x = init.positions(sc, np.arange(sc.n, dtype=np.int64))
    r2 = ((x[:, None, :] - x[None, :, :]) ** 2).sum(-1)
    actual = (np.count_nonzero(r2 < 1.0) - sc.n) / 2
    est = footprint.pairs_within(sc, 1.0)
    tol = 0.06 if sc.init.kind == "gaussian" else 0.25  # the lattice's boundary is ignored (upper bound)
    assert abs(est - actual) <= tol * actual, (est, actual)


def test_too_dense_start_is_refused_with_a_spread(tmp_path):
    proc = cli(["check", "--set", "n=20000", "--set", "init.sigma=1.0", "--set", "neighbor.max_pair_gib=0.5"], tmp_path)
    assert proc.returncode == 2, describe(proc)
    err = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(err) == 1 and "too dense for memory" in err[0] and "init.sigma to at least" in err[0], describe(proc)
    sigma = float(err[0].split("at least ")[1].split(",")[0])
    # the suggested spread fits
    proc = cli(["check", "--set", "n=20000", "--set", f"init.sigma={sigma}", "--set", "neighbor.max_pair_gib=0.5"],
               tmp_path)
    assert proc.returncode in (0, 3), describe(proc)
    assert "-> fits" in proc.stdout


# ---- the command line ---------------------------------------------------------------------------
def test_check_cli_exit_codes(tmp_path):
    proc = cli(["check", "two-spheres"], tmp_path)
    assert proc.returncode == 0, describe(proc)
    assert "## Resolved scene" in proc.stdout and 'name = "two-spheres"' in proc.stdout
    assert "Verdict: STABLE" in proc.stdout and "margin" in proc.stdout
    # the paper's N = 2000 parameters: the packed state is predicted unstable (measured: overlap
    # bursts from iteration 5856 on, research/FINDINGS.md section 1)
    proc = cli(["check", "paper-2d"], tmp_path)
    assert proc.returncode == 3, describe(proc)
    assert "Verdict: NOT STABLE" in proc.stdout
    # the main job's schedule bounds every step by that iteration's stiffest row
    proc = cli(["check"], tmp_path)
    assert proc.returncode == 0, describe(proc)
    assert "Verdict: STABLE by construction" in proc.stdout and 'schedule = "fire-al"' in proc.stdout
    for args, word in ((["check", "--set", "method.alpha=-1"], "method.alpha"),
                       (["check", "no-such-scene"], "unknown scene"),
                       (["check", "--set", "nosuch=1"], "nosuch")):
        proc = cli(args, tmp_path)
        assert proc.returncode == 2, describe(proc)
        lines = [line for line in proc.stderr.splitlines() if line.strip()]
        assert len(lines) == 1 and lines[0].startswith("mpipack: error:") and word in lines[0], describe(proc)
        assert proc.stdout == ""


def test_check_under_mpirun_prints_once(tmp_path):
    proc = mpirun(2, [sys.executable, "-m", "mpipack.cli", "check", "two-spheres"], cwd=tmp_path)
    assert proc.returncode == 0, describe(proc)
    assert proc.stdout.count("## Resolved scene") == 1
    assert "on 2 rank(s)" in proc.stdout or "2 rank(s)" in proc.stdout


@pytest.mark.parametrize("potential,nap_line", [('kind = "point"\npoint = [-1.0, -1.0]', False),
                                                ('kind = "gravity"\ng = 1.0', True)])
def test_check_of_a_nested_method_in_a_container_says_its_estimate_is_a_guide(tmp_path, potential, nap_line):
    """NAP in a box: the cluster's linearisation is the trap's, without walls; under gravity NAP
    circles a floor's fixed point (tests/test_container_nested.py), which check says."""
    scene = tmp_path / "nap-box.toml"
    scene.write_text('name = "nap-box"\ndim = 2\nn = 30\nseed = 1\n[method]\nname = "nap"\nform = "NS"\n'
                     'alpha = 0.1\nbeta = 0.16\nl_inner = 1000\n[container]\nkind = "box"\nlo = [-3.0, -3.0]\n'
                     f'hi = [3.0, 3.0]\n[potential]\n{potential}\n')
    proc = cli(["check", scene], tmp_path)
    assert proc.returncode == 0, describe(proc)
    assert "they are a guide only" in proc.stdout and "container.kind = 'box'" in proc.stdout, proc.stdout
    assert ("NAP has no damping" in proc.stdout) == nap_line
