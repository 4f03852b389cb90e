"""``mpipack check SCENE``: validate a scene as ``run`` does, print it resolved, and judge its
parameters before a run: a stability verdict with its margin, the overlapping pairs of the
start and the memory per rank. Exit 0 when the verdict is stable, 3 when it is not, 2 for bad
input (one line ``mpipack: error: ...``, also for a start too dense for memory).

Nothing here iterates the solver: every number is a formula or a small eigenvalue problem.

The mathematics are in ``analysis.stability``, the start's cost in ``analysis.footprint``;
this module writes the report and is the command.
"""

import math
import sys

from mpipack.analysis.footprint import BYTES_PER_ENTRY, start_and_memory
from mpipack.analysis.stability import (TOL, _is_stable, _is_stable_estimate, buckling_ratio, cluster_n,
                                        packed_state, verdict, with_param)
from mpipack.errors import EXIT_INPUT, EXIT_OK, EXIT_UNSTABLE


# ---- text -----------------------------------------------------------------------------------------
def _toml_value(v):
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, float):
        return repr(v) if math.isfinite(v) else ("inf" if v > 0 else "-inf" if v < 0 else "nan")
    return str(v)


def scene_toml(table):
    """The resolved scene as TOML text (keys without a value as comments)."""
    lines, sections = [], []
    for k, v in table.items():
        if isinstance(v, dict):
            sections.append((k, v))
        elif v is None:
            lines.append(f"# {k} = (not set)")
        else:
            lines.append(f"{k} = {_toml_value(v)}")
    for name, sec in sections:
        lines.append(f"\n[{name}]")
        for k, v in sec.items():
            lines.append(f"# {k} = (not set)" if v is None else f"{k} = {_toml_value(v)}")
    return "\n".join(lines)


def _fmt_roots(z, discrete=True):
    parts = []
    for r in sorted(z, key=lambda w: -abs(w)):
        if abs(r.imag) > 1e-14 * max(1.0, abs(r)):
            if r.imag < 0:
                continue
            parts.append(f"{r.real:.4g} ± {abs(r.imag):.4g}i" + (f" (|z| = {abs(r):.6f})" if discrete else ""))
        else:
            parts.append(f"{r.real:.6g}")
    return ", ".join(parts)


def _fmt_poly(coef):
    k = len(coef) - 1
    terms = []
    for i, c in enumerate(coef):
        p = k - i
        if c == 0:
            continue
        mono = "" if p == 0 else ("s" if p == 1 else f"s^{p}")
        num = "" if (c == 1 and p > 0) else f"{c:.4g}"
        terms.append((num + " " + mono).strip())
    return " + ".join(terms)


def _gib(x):
    return f"{x / 2 ** 30:.3g} GiB" if x >= 2 ** 27 else f"{x / 2 ** 20:.3g} MiB"


def report_lines(scene, ranks):
    """(stable, lines, memory dict) for rank 0 to print."""
    m = scene.method
    L = []
    tag = f"{m.name.upper()}-{m.form}"
    L.append("## Stability")
    if m.schedule == "fire-al":
        stable = True
        L.append("Schedule fire-al: no fixed parameters to judge. Each iteration's step is bounded by "
                 "the stiffest row of that iteration (FIRE's dt <= sqrt(1/k_rel), k_rel the reduced "
                 "largest Gershgorin row of the augmented Lagrangian, momentum restarted when the power "
                 "turns negative); the explosion of a dense start uses the gamma term's CFL bound at the "
                 "packing law's multipliers (mpipack/methods/fire_al.py).")
        if scene.potential.kind == "gravity":
            from mpipack.methods.fire_al_schedule import scene_law
            law = scene_law(scene)
            L.append(f"Under gravity the law is the bed's: height H = {law['radius']:.4g} over the floor at the "
                     f"law's packing fraction, W_eq = g N m H / 2 = {law['W']:.4g}, mean multiplier "
                     f"{law['lam_bar']:.4g} (the virial identity with the floor carrying the weight; "
                     f"fire_al_schedule.scene_law); the walls' rows count in the Gershgorin bound like pairs'.")
        elif scene.container.active:
            L.append("In a container the walls' rows count in the Gershgorin bound like pairs', and a dense "
                     "start is first spread over the container (fire_al_schedule.scene_law).")
        L.append(f"Verdict: STABLE by construction ({tag}, N = {scene.n}, dim {scene.dim}; schedule fire-al)")
        start, mem = _start_lines(scene, ranks)
        return stable, L + start, mem
    stable, rep = verdict(scene)
    two = rep["two"]
    if two is not None:
        L.append(f"Two free spheres (exact for N = 2; d = {two['d']:.6g}): fixed point r = d, lambda = "
                 f"{two['lambda']:.6g}")
        if m.nested:
            L.append("  the inner loop (linearised constraints about X^p = the fixed point); the outer "
                     "iteration then converges in one step (NS) or quadratically (S) (paper, Appendix A)")
        poly = two["ode"]
        L.append(f"  ODE: characteristic polynomial {_fmt_poly(poly)}")
        L.append(f"       roots {_fmt_roots(two['ode_roots'], discrete=False)}: "
                 f"{'asymptotically stable' if two['ode_ok'] else 'NOT asymptotically stable'}")
        if two["ode_condition"] is not None:
            text, lhs, rhs, ok = two["ode_condition"]
            L.append(f"       Routh-Hurwitz {text}: {lhs:.4g} vs {rhs:.4g} ({'holds' if ok else 'fails'})")
        if two["paper_condition"] is not None:
            text, lhs, rhs, ok = two["paper_condition"]
            L.append(f"       (the paper's one-sphere-fixed condition, section 3: {text}: {lhs:.4g} vs {rhs:.4g}, "
                     f"{'holds' if ok else 'fails'})")
        L.append(f"  scheme as it runs (linearised in y^n, y^(n-1), mu^(n-1)): K = {two['K']:.4g}, q = {two['q']:.4g}, "
                 f"momentum m = {two['m']:.4g}")
        L.append(f"       eigenvalues {_fmt_roots(two['z'])}: spectral radius {two['rho']:.6f} -> "
                 + ("stable" if two["ok"] else "NOT stable")
                 + (f", error / e every {1.0 / -math.log(two['rho']):.3g} iterations" if 0 < two["rho"] < 1 - TOL else ""))
        if two["ok"] != two["ode_ok"]:
            L.append("       the ODE and the scheme disagree at this step size; the verdict uses the scheme")
    if rep["cluster"] is not None and rep["packed"] is None:
        c = rep["cluster"]
        L.append(f"N = {scene.n} spheres: {c['text']} -> {'stable' if c['ok'] else 'NOT stable'}")
    if rep["packed"] is not None:
        pk = rep["packed"]
        L.append(f"N = {scene.n} spheres, the packed state (estimate): radius R = {pk['R']:.4g}, mean-field row "
                 f"stiffness at the centre {pk['s_centre']:.4g}, largest eigenvalue of J^T Lambda J ~ "
                 f"{pk['kappa']:.2f} x that = {pk['k_est']:.4g}")
        for c in pk["conditions"]:
            L.append(f"  {c['name']}: {c['text']} -> {'ok' if c['ok'] else 'FAILS'}")
        if m.name == "daha" and m.c < 2:
            K_w = m.alpha ** 2 / (1 + 0.5 * m.c)
            q = pk.get("q", 0.0)
            mom = (1 - 0.5 * m.c) / (1 + 0.5 * m.c)
            L.append(f"  momentum (c = {m.c:g} < 2): a weakly loaded contact (K -> {K_w:.3g}) is linearly unstable "
                     f"when q > (1 - m) K = {(1 - mom) * K_w:.3g} (here q = {q:.3g}); measured: small N may "
                     f"still certify (N = 100 NS: c = 1, 0.5 yes, 0.2 no; N = 7: c = 1 yes, 0.5 no), N = 2000 "
                     f"with no c < 2 tried (research). Not part of the verdict")
        L.append("  the packed-state figures are estimates calibrated on packings made by mpipack run (see "
                 "`mpipack.analysis.check`); two free spheres bound nothing for N > 2")
    if (scene.container.active or scene.potential.kind != "centre") and (rep["packed"] or rep["cluster"]):
        L.append(f"  these estimates are those of the paper's W (the trap) without walls; with potential.kind = "
                 f"{scene.potential.kind!r} and container.kind = {scene.container.kind!r} they are a guide "
                 f"only: a wall's row adds at most a pair's, and gravity's W has no curvature (its term in "
                 f"the bound is alpha^2 x 0); the fire-al schedule needs no such estimate")
        if m.name == "nap" and scene.potential.kind == "gravity":
            L.append("  NAP has no damping: where W is flat along a direction the walls hold (a sphere on a "
                     "floor under gravity) it circles the fixed point instead of settling; NAV settles there")
    margin = _margin_lines(scene, stable)
    basis = ("two free spheres, the scheme as it runs" if scene.n == 2 else
             "the scheme linearised at the close-packed cluster" if rep["packed"] is None and scene.n > 2 else
             ("packed-state estimate and a smaller cluster" if rep["cluster"] is not None else "packed-state estimate")
             if scene.n > 2 else "nothing to iterate")
    L.append(f"Verdict: {'STABLE' if stable else 'NOT STABLE'} ({tag}, N = {scene.n}, dim {scene.dim}; {basis})")
    L += margin
    start, mem = _start_lines(scene, ranks)
    return stable, L + start, mem


def _start_lines(scene, ranks):
    """The report's start and memory section: (lines, memory dict)."""
    L = []
    mem = start_and_memory(scene, ranks)
    L.append("")
    L.append("## Start and memory")
    kind = scene.init.kind
    if kind == "gaussian":
        L.append(f"Gaussian start, sigma = {mem['sigma']:.4g}: each pair's separation is N(0, 2 sigma^2 I)")
    elif kind == "ball":
        L.append("uniform ball start (an upper bound: boundary effects ignored)")
    elif kind == "file":
        L.append(f"start from {scene.init.file}"
                 f"{f' (snapshot {scene.init.iteration})' if scene.init.iteration is not None else ''}: "
                 f"its pairs counted")
    else:
        L.append(f"lattice start, spacing {scene.init.spacing:g} (jitter ignored)")
    n = scene.n
    L.append(f"  overlapping pairs at the start ~ {mem['overlapping_pairs']:.4g} "
             f"({2 * mem['overlapping_pairs'] / n:.3g} per sphere)")
    L.append(f"  pair-row entries (pairs within d_kl + skin, the start's skin {mem['start_skin']:g} d_max; "
             f"twice) ~ {2 * mem['row_pairs']:.4g}, "
             f"{mem['entries_per_rank']:.4g} per rank on {ranks} rank(s)")
    L.append(f"  memory per rank: particles {_gib(mem['particles_bytes'])} + rows {_gib(mem['entries_per_rank'] * BYTES_PER_ENTRY)} "
             f"= {_gib(mem['steady_bytes'])}; while rows are built up to {_gib(mem['peak_bytes'])}; "
             f"budget {_gib(mem['budget_bytes'])} per rank "
             f"({'neighbor.max_pair_gib' if scene.neighbor.max_pair_gib is not None else 'available memory / ranks'})"
             f" -> {'fits' if mem['fits'] else 'DOES NOT FIT'}")
    if mem["suggested_sigma"] is not None:
        L.append(f"  suggested spread: init.sigma >= {mem['suggested_sigma']:.4g} (rows within 80% of the budget), "
                 f"or more ranks/nodes, or init.kind = \"ball\"")
    return L, mem


def _daha_gamma_window(scene):
    """N > 2, DAHA: (gamma_min, gamma_max) allowed by the buckling ratio and the stiffness of the
    packed state at this alpha, beta, c (gamma_max None when no gamma passes the stiffness)."""
    m = scene.method
    lim = buckling_ratio(scene.n) if scene.dim >= 2 else 0.0
    g_min = m.alpha / lim if lim > 0 else 0.0

    def stiff_ok(g):
        c = packed_state(scene.replace(method={"gamma": g}))["conditions"][0]
        return c["ok"]

    lo, hi = max(g_min, 1e-12), None
    if not stiff_ok(lo):
        return g_min, None
    g = lo
    while g < 1e6:
        if not stiff_ok(g * 1.25):
            a, b = g, g * 1.25
            for _ in range(60):
                mid = math.sqrt(a * b)
                a, b = (mid, b) if stiff_ok(mid) else (a, mid)
            hi = a
            break
        g *= 1.25
    return g_min, hi


def _edge(ok, v, factor, steps=10, bisect=8):
    """The last value for which ok() holds going from v (ok) by factor per step, refined by
    bisection in log; None if ok holds for all ``steps`` steps."""
    a = v
    for _ in range(steps):
        b = a * factor
        if not ok(b):
            for _ in range(bisect):
                mid = math.sqrt(a * b)
                a, b = (mid, b) if ok(mid) else (a, mid)
            return a
        a = b
    return None


def _margin_lines(scene, stable):
    """How far the parameters are from the edge, or a change that would make them stable."""
    m = scene.method
    out = []
    n = scene.n
    if n == 1:
        return out
    if n > 2 and m.name == "aha" and scene.dim >= 2:
        return ["  AHA cannot be stable in 2D/3D (no augmentation term): use method.name = \"daha\""]
    if n > 2 and cluster_n(scene) < n and m.name == "daha":
        return _window_lines(scene, stable)
    exact = n == 2 or cluster_n(scene) >= n
    keys = (["gamma", "beta", "alpha"] if m.name == "daha" else ["beta", "alpha"]) if n == 2 else \
        (["gamma"] if m.name == "daha" else ["beta"])
    if not exact:  # NAP/NAV at large N: the estimate's inner-loop condition
        keys = ["beta"]
    judge = _is_stable if exact else _is_stable_estimate
    if stable:
        parts = []
        for key in keys:
            v = getattr(m, key)
            if v <= 0:
                continue

            def ok(x, key=key):
                return judge(with_param(scene, key, x))
            hi = _edge(ok, v, 2.0)
            lo = _edge(ok, v, 0.5)
            parts.append(f"{key} in [{'0' if lo is None else f'{lo:.4g}'}, {'>1e3 x' if hi is None else f'{hi:.4g}'}]"
                         + (f" (x{hi / v:.3g} of room above" if hi is not None else " (")
                         + (f", x{v / lo:.3g} below)" if lo is not None else ")"))
        if parts:
            out.append("  margin (each parameter alone, the others fixed): " + "; ".join(parts))
        return out
    fixes = []
    for key in keys:
        v = getattr(m, key)
        if v <= 0:
            continue
        for f in (0.8, 0.5, 0.3, 0.1, 0.03, 1.25, 2.0, 4.0):
            if judge(with_param(scene, key, v * f)):
                fixes.append(f"method.{key} = {v * f:.4g}")
                break
    if m.name == "daha" and m.gamma == 0:  # gamma = 0 scales to nothing: try alpha/gamma = 0.5, ... and sqrt(alpha beta)
        for g, why in ((2 * m.alpha, "alpha/gamma = 0.5"), (3 * m.alpha, "alpha/gamma = 1/3"),
                       (math.sqrt(m.alpha * m.beta), "sqrt(alpha beta)")):
            if judge(scene.replace(method={"gamma": g})):
                fixes.append(f"method.gamma = {g:.4g} ({why})")
                break
    if fixes:
        out.append("  stable instead with one change: " + " or ".join(fixes))
    else:
        out.append(f"  no single change of {', '.join(keys)} by x0.03-x4 makes it stable")
    return out


def _window_lines(scene, stable):
    """DAHA at large N: the gamma window of the estimate (buckling below, stiffness above)."""
    m = scene.method
    out = []
    g_min, g_max = _daha_gamma_window(scene)
    if g_max is not None and g_max >= g_min:
        where = (f"gamma = {m.gamma:.4g} has x{g_max / m.gamma:.3g} of room above and x{m.gamma / g_min:.3g} below"
                 if g_min <= m.gamma <= g_max and g_min > 0 else f"gamma = {m.gamma:.4g} is outside it")
        out.append(f"  gamma window at this alpha, beta, c (estimate): [{g_min:.4g} (buckling, alpha/gamma <= "
                   f"{buckling_ratio(scene.n):.2f}), {g_max:.4g} (stiffness)]: {where}")
        if not stable and not (g_min <= m.gamma <= g_max):
            out.append(f"  stable instead (estimate) with method.gamma = {math.sqrt(max(g_min, 1e-300) * g_max):.4g}")
    else:
        def window_open(a):
            gmn, gmx = _daha_gamma_window(with_param(scene, "alpha", a))
            return gmx is not None and gmx >= gmn
        a_lo = _edge(lambda a: not window_open(a), m.alpha, 0.7, steps=40, bisect=20)
        if a_lo is not None:
            a_ok = 0.9 * a_lo
            gmn, gmx = _daha_gamma_window(with_param(scene, "alpha", a_ok))
            out.append(f"  no gamma is stable at alpha = {m.alpha:.4g} (the buckling bound {g_min:.4g} is above the "
                       f"stiffness bound{'' if g_max is None else f' {g_max:.4g}'}): stable instead (estimate) with "
                       f"method.alpha <= {a_lo:.4g}, e.g. alpha = {a_ok:.4g} and gamma = {math.sqrt(gmn * gmx):.4g}")
        else:
            out.append("  no alpha down to x1e-6 opens a stable gamma window at this N (estimate)")
    out.append("  (the window comes from the packed-state estimate, a guide: check it with a run, "
               "mpipack run --set output.metrics_every=100 records the max overlap over the run)")
    return out


# ---- command line ----------------------------------------------------------------------------------
def main(args, rank=0):
    """``mpipack check``: returns the exit code; prints on rank 0 only."""
    from mpipack import config
    try:
        scene = config.load(args.scene, args.overrides, args.seed)
    except config.SceneError as e:
        if rank == 0:
            print(f"mpipack: error: {e}", file=sys.stderr, flush=True)
        return EXIT_INPUT
    from mpipack.parallel.launcher import world_size
    ranks = args.ranks or world_size()
    stable, lines, mem = report_lines(scene, ranks)
    if rank == 0:
        m = scene.method
        print(f"mpipack check: scene {scene.name}: {m.name.upper()}-{m.form} dim={scene.dim} N={scene.n}, "
              f"{ranks} rank(s)\n")
        print("## Resolved scene\n")
        print(scene_toml(scene.as_dict()))
        print()
        print("\n".join(lines), flush=True)
    from mpipack.engine.memory import BYTES_PER_PARTICLE
    if mem["particles_bytes"] > mem["budget_bytes"]:
        if rank == 0:
            print(f"mpipack: error: n = {scene.n} spheres need about {_gib(mem['particles_bytes'])} per rank for the "
                  f"particle arrays alone ({BYTES_PER_PARTICLE[scene.dim]} B each), more than the "
                  f"{_gib(mem['budget_bytes'])} available per rank; use more ranks or nodes, or fewer spheres",
                  file=sys.stderr, flush=True)
        return EXIT_INPUT
    if not mem["fits"]:
        if rank == 0:
            hint = (f"raise init.sigma to at least {mem['suggested_sigma']:.4g}" if mem["suggested_sigma"]
                    else "spread the start")
            print(f"mpipack: error: the start is too dense for memory: its pair rows need about "
                  f"{_gib(mem['peak_bytes'])} per rank while they are built, more than the "
                  f"{_gib(mem['budget_bytes'])} available; {hint}, use more ranks or nodes, or "
                  f"set neighbor.max_pair_gib", file=sys.stderr, flush=True)
        return EXIT_INPUT
    return EXIT_OK if stable else EXIT_UNSTABLE
