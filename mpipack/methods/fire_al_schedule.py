"""The decisions of the "fire-al" schedule (``method.schedule = "fire-al"``): parameters that
need no tuning, set every iteration from the figures of the previous one. The method object
that runs them on the state is ``methods.fire_al.FireAL``. No MPI, no arrays: every input is a
reduced number, so every rank takes the same decisions (bitwise rank-count independence).

Why (docs/research/convergence.md has the measurements): with fixed (alpha, beta, gamma, c) DAHA is
stable only while alpha^2 Hess L + gamma^2 J^T Lambda J has its largest eigenvalue below 4;
the multipliers grow like the pressure, ~R^2 ~ N^(2/b), so any fixed set leaves the stability
region as N grows, and momentum (c < 2) with the lambda-weighted gamma term makes weakly loaded
contacts chatter. The schedule therefore spreads a dense start, explodes what overlap
remains, then relaxes with FIRE on an augmented Lagrangian.

Law (from N, b, the mean diameter d and the form; a uniform ball of packing fraction phi_p =
1, 0.85, 0.64 in 1D, 2D, 3D, about b N contacts, and the virial identity of a KKT point,
S: sum lambda d^2 = W, NS: sum lambda d = 2W):

    R = d/2 (N/phi_p)^(1/b),  W_eq = N b R^2 / (2(b+2)),
    lam_bar = W_eq / (b N d^2) (S)  or  2 W_eq / (b N d) (NS),  g2 = 4 d^2 (S) or 1 (NS)

0. Spread (a start whose first max overlap exceeds 0.5 d and whose W is below that of a uniform
   ball of radius SPREAD R, SPREAD = sqrt 6: a sixth of the packing's density in 2D; a 2D
   jammed finish 2 R, JAMMED_SPREAD): every
   centre moves along its ray from Xbar to SPREAD R F(r)^(1/b), F the cloud's radial
   distribution (an exact histogram summed over ranks): a uniform dilute ball, directions and
   the order of radii kept (``init.equalise_radially``). A dense Gaussian start otherwise
   explodes by diffusion (kicks of ~10 d in random directions), thousands of iterations at
   N = 1e5, and a homothety would put its tail (the farthest of N at sqrt(2 ln N) sigma) far
   out, so that the fall back takes longer.

1. Explosion (only for a start whose first max overlap exceeds 0.5 d): paper DAHA with c = 2,
   gamma = alpha = sqrt(2 theta / S_law), S_law = kappa g2 2b lam_bar (the CFL of the gamma
   term at the law's row stiffness; the weight of grad W is alpha^2 d^p: p = 2 (S), 1 (NS)),
   beta = q_e / (a3 T) with T the reduced largest dual gain of a row, q_e = 100 for a dense
   start, 1 after the spread (the remaining overlaps are isolated pairs: separate them, do not
   fling them across the gas); until the max overlap is below 0.1 d or W exceeds 10 W_eq (an
   explosion that overshoots: in 1D it would fly to 1000 W_eq). Then lambda := 0 and
   X^{n-1} := X^n.

2. FIRE on the augmented Lagrangian L_rho (``kernels_fire``, clip form) with per-pair penalty
   rho = c_b max(lambda, lam_fl) / d_ij^p (phi has the units of d^p), lam_fl = f lam_bar; while
   c_b is at its start (4 in 1D and 2D, 16 in 3D), a continuous dual step lambda <- max(0, lambda + omega rho phi)
   every iteration; a multiplier (ALM) step lambda <- max(0, lambda + rho phi) (one pass, penalty
   off) when the inner residual r_in = ||grad L_rho|| / ||grad W|| <= eta (eta from 0.3, halved
   at each ALM step, floor 0.003) and at least 20 iterations since the last, or after MAX_INNER
   iterations without one (the first: FIRST_INNER iterations after the fall from the spread
   ball, ~2 (SPREAD - 1) R / VMAX iterations, is over), unless the max overlap is already within
   HOLD_OVERLAP times the stop's overlap tolerance: then the multipliers do what they are for,
   and what remains is the inner solve's stationarity, which a forced step would only disturb.
   At an ALM step whose max overlap is above half that of the step before (the multipliers did
   not gain on the overlap), c_b doubles (x8 in 3D; up to 1024) and the
   continuous dual stops: in a disordered packing (3D, mixed sizes) the soft penalty lets
   contacts slide and rearrange after every multiplier step, and the continuous dual's small
   kicks keep the inner problem from settling; a stiffer penalty freezes the contact network so
   that the multiplier steps converge (docs/research/convergence.md, section 3c). A 3D packing is a glass
   whatever the soft phase does (the soft phase anneals a 2D crystal, section 3c), so 3D starts
   stiffer and stiffens faster: 3D N = 2000 and 8000 certify 2.1x and 1.5x sooner (section 3g).
   FIRE (Bitzek et al. 2006) in displacement form:
       X^{n+1} - X^n = a (X^n - X^{n-1}) + b G,    G = -grad L_rho,   |step_i| <= vmax d
       a = (1 - mix) dt / dt_prev,   b = (1 - mix) dt^2 + mix dt^2 |V| / (dt |G|)
   power G.V < 0: X^{n-1} := X^n, dt /= 2, mix = 0.1; after 5 positive iterations
   dt = min(1.1 dt, dt_max), mix *= 0.99; dt_max = 2 / sqrt(k_rel), k_rel = K / b with K the
   reduced largest Gershgorin row of the step (so dt_max tracks the stiffest contact): the
   leapfrog bound dt^2 lambda_max < 4 with Gershgorin's k_rel >= lambda_max (a margin of 2 on dt,
   as before, cost 3 - 8 times more iterations at N = 8000: docs/research/convergence.md, section 3d).

3. L-BFGS on the stiff penalty: from the multiplier step at which c_b reaches
   QN_FROM_CB (the cap, 1024, in 1D and 3D; 256 in 2D), the inner solves are L-BFGS's (``qn``:
   memory m pairs, the two-loop recursion on the Gram matrix of exact sums, one reduction per
   iteration; ``kernels_qn``) instead of FIRE's. In the stiff phase FIRE's step is bounded by
   the stiffest contact (c_b lambda |grad phi|^2) while the packing creeps along soft modes only
   the trap holds; a quasi-Newton direction learns their curvature from its last steps
   (docs/research/convergence.md, sections 3k, 3q and 3r). A multiplier step
   then resets the memory (L_rho changed); it is forced after QN_MAX_INNER iterations while the
   max overlap is above the stop's tolerance (the inner solve has converged as far as it will;
   only the multipliers bring the overlap under it), after MAX_INNER between the hold and the
   tolerance. In 2D it is damped, lambda <- max(0, lambda + QN_DUAL_STEP rho phi) with
   QN_DUAL_STEP = 1/2: the creeping phase's inner solves end far from converged, and a full step
   over-corrects.

Fixed points: at a KKT point the clip gives the force multiplier lambda, grad L_rho = grad L =
0, both dual steps leave lambda unchanged and every step is zero: the fixed points are those of
the paper (Proposition 2.4). The certificate's multipliers are the force multipliers
max(0, lambda + rho phi) of the pairs in contact to the overlap tolerance (``force_multiplier``;
the first-order estimate of augmented Lagrangian codes): the stored lambda lags a multiplier
step behind, so that between two steps a converged inner solve could not be certified.
"""

import dataclasses
import enum
import math
from typing import NamedTuple

from mpipack.methods import lbfgs as qn

# explosion
THETA, KAPPA, Q_EXPLODE, OV_START, OV_END = 0.3, 8.0, 100.0, 0.5, 0.1
EXPLODE_CAP = 0.25  # no sphere moves more than this fraction of the law's radius per iteration
W_SWITCH = 10.0  # ... or once W exceeds this multiple of the law's W (an overshooting explosion)
# a start whose W is below that of a uniform ball of radius SPREAD R (the law's radius) is first
# spread into such a ball about its centre of mass (in 2D: a sixth of the packing's density)
SPREAD = math.sqrt(6.0)
Q_GENTLE = 1.0  # the explosion's gain once the start is a dilute ball: separate pairs, no kicks
# augmented Lagrangian and FIRE
# OMEGA: the continuous dual step's gain; 0.02 hardens a contact in ~50 iterations, before the
# sliding spheres of a large packed core (up to 0.02 d per iteration) have left it (0.01: 2D
# N = 8000 cores flowed for 8000 iterations at overlaps of 0.1 - 0.2 d; 0.03: 3D N = 2000 jammed
# looser, 3x slower; 0.1: chatter, 10x the restarts; docs/research/convergence.md, section 3d)
FLOOR, OMEGA, VMAX = 3.0, 0.02, 0.02
N_DELAY, F_INC, F_DEC, MIX0, F_MIX, DT0_FRAC = 5, 1.1, 0.5, 0.1, 0.99, 0.1
ETA0, ETA_F, ETA_MIN, MIN_INNER = 0.3, 0.5, 0.003, 20
# a multiplier step is forced after MAX_INNER iterations without one (0: never forced), the
# first after FIRST_INNER beyond the fall (a long soft phase packs denser), but not while the
# max overlap is within HOLD_OVERLAP x stop.overlap: a stiff glass creeps (its contact forces
# keep redistributing), so that its inner solve may never reach eta; the forced steps then
# carry the overlap down, and once it is within tolerance they only disturb the force balance
# the certificate needs (docs/research/convergence.md, section 3e)
MAX_INNER, FIRST_INNER, HOLD_OVERLAP = 1500, 3000, 0.5
# the penalty factor c_b grows (x CB_GROW) at a multiplier step whose max overlap is above PEN_GROW
# times that of the step before (the multipliers did not gain on the overlap), up to CB_MAX; the
# continuous dual step runs only while c_b is at its start
# (1024: a multiplier step at overlap delta changes the pair's multiplier by 2 c_b delta lambda
# (S), so that at 256 the certificate's 1e-3 d needed the creeping glass's contact forces to
# settle to within half between two steps; 3D N = 8000 certified 1 run of 3 at 256)
PEN_GROW, CB_MAX = 0.5, 1024.0
# the penalty factor's start C_B and its growth factor CB_GROW by dimension: 3D starts at 16 and
# grows x8 (3D N = 2000 seeds 0 - 9: median 8500 iterations against 17875 with (4, x2); N = 8000
# seeds 0 - 4: 15950 against 23825; 3D N = 100 and 500 a little slower in median, 3625 and 6100
# against 2650 and 5325, with shorter worst cases; docs/research/convergence.md, section 3g). In 2D the same
# pair is slower (N = 2000: 5125, and 3275 with x8 alone, against 2675): the soft phase
# anneals a crystal there
C_B = {1: 4.0, 2: 4.0, 3: 16.0}
CB_GROW = {1: 2.0, 2: 2.0, 3: 8.0}
# once c_b reaches QN_FROM_CB, the inner solves are L-BFGS's instead of FIRE's (``qn``): in the
# stiff phase FIRE's step is bounded by the stiffest contact and the packing creeps along its
# soft modes (the trap's); a quasi-Newton direction learns their curvature from its last steps
# (docs/research/convergence.md, sections 3k and 3q). Under a softer penalty a glass keeps rearranging
# after every multiplier step and the quasi-Newton steps carry it away (3D from 128: 3D N = 8000
# seed 3 not certified); a 2D packing holds from 256 (2D N = 32000 seeds 0 - 4 and the mixed
# sizes sooner in sum than from the cap; docs/research/convergence.md, section 3r)
QN_FROM_CB = {1: CB_MAX, 2: 256.0, 3: CB_MAX}
# ... whose multiplier step is forced after QN_MAX_INNER iterations while the max overlap is
# above the stop's tolerance (the inner solve converges, but only a multiplier step brings the
# overlap under the tolerance, without which nothing can be certified), after MAX_INNER while
# it is between the hold and the tolerance
QN_MAX_INNER = 500
# ... and in 2D its multiplier step is damped, lambda <- max(0, lambda + QN_DUAL_STEP rho phi):
# the inner solves of the creeping phase end far from converged (the inner residual at 2 - 7
# times |grad W| at 2D N = 1e5), and a full step over-corrects the multipliers, whose next inner
# solve partly undoes the motion the last one made (docs/research/convergence.md, section 3s: 2D N = 32000
# seeds 0 - 6 12% fewer iterations in sum, six seeds sooner or the same; the 2D mixed sizes 3%).
# In 3D it did not clearly pay (N = 2000 seeds 0 - 9 7% fewer, N = 8000 seeds 0 - 4 1% more).
# A fixed point is unchanged: at a KKT point phi lambda = 0, phi <= 0, and lambda stays
QN_DUAL_STEP = {1: 1.0, 2: 0.5, 3: 1.0}
# the quench of a jammed finish (``stop.rule = "jammed"``, 3D): the first multiplier step as soon
# as W has settled, |W^n - W^(n - QUENCH_WINDOW)| <= QUENCH_SETTLED W^n, checked every
# QUENCH_WINDOW iterations of the fire phase (instead of FIRST_INNER beyond the fall, which packs
# denser for the certificate), then a multiplier step forced after QUENCH_MAX_INNER iterations
# and c_b grown at every one (the overlap down to stop.overlap at once, as a two-stage quench
# raises its stiffness): 3D N = 1e4 seeds 1 - 4 jam after 1900 - 2350 iterations against
# 8250 - 9250, W 0.1 - 0.3% below LAMMPS's two-stage quench (QUENCH_MAX_INNER 300: 2250 - 2850;
# 150 and 100 no better). In 2D, from the sqrt(6) R ball, a quench did not pay (session 28: N =
# 2000 and 2e4, seeds 1 - 3, about the same iterations, W higher; docs/benchmarks.md, "Jammed
# finish"). 2D quenches too since session 30, from a smaller spread
# ball (JAMMED_SPREAD below): N = 2e4 seeds 1 - 4 then jam after 6539 - 7214 iterations against
# 7283 - 16042 (the first multiplier step waited FIRST_INNER beyond the fall whenever the inner
# residual missed eta), N = 2000 seeds 5 - 12 after 1803 - 2092 against 2228 - 2502
QUENCH = {1: False, 2: True, 3: True}
QUENCH_WINDOW, QUENCH_SETTLED, QUENCH_MAX_INNER = 100, 1e-3, 200
# ... and QUENCH_MAX_INNER (R / QUENCH_RADIUS)^2 beyond QUENCH_RADIUS (R the law's radius, d's),
# as every forced step's wait at most MAX_INNER (FIRE's inner solves) or QN_MAX_INNER (L-BFGS's):
# a large packing's inner solve needs longer to relax a multiplier step's change across it (a
# damped relaxation's time grows like the area). 2D N = 2e5 (R = 242.5 d; 2 ranks, seed 1) with
# 200 wandered at max overlaps of 0.2 - 0.4 d for 23000 iterations after its quench and jammed
# after 47934, 4.9% above the certified W; waits of 600, 1200 and this rule's 1999 (FIRE's 600,
# 1200, 1500, L-BFGS's 500 in each) after 30695, 32242, 35236, 3.9%, 2.0%, 1.2% above. At 2D
# N = 2e4 (R = 76.7 d) 383 took 7 - 18% more iterations than 200 on seeds 1 - 3
# (docs/benchmarks.md, session 43). 3D (R = 34 d at N = 2e5) and 2D up to N = 2e4 keep 200
QUENCH_RADIUS = 76.7
# the spread ball's radius (in law radii) of a jammed finish: the fall back from SPREAD R at the
# speed cap VMAX was ~3/4 of a 2D jammed run (N = 2000: iterations ~1800 of 2300). In 2D a ball
# of 2 R (a fourth of the packing's density) falls in ~2/3 of the time and still separates
# cleanly (N = 2000 seeds 1 - 12: 1719 - 1925 iterations without the quench; 1.8 R and 1.6 R:
# 3245 and 4301 on one seed each of 4, not looked into). In 3D a 2 R ball
# jams 17% sooner but looser, W 0.04 - 0.2% above LAMMPS's quench on 3 seeds of 4 (N = 1e4):
# kept at SPREAD. docs/benchmarks.md, "A 2D jammed finish sooner than the quench (session 30)"
JAMMED_SPREAD = {1: SPREAD, 2: 2.0, 3: SPREAD}
# FIRE's dt_max = DT_LEAPFROG / sqrt(k_rel): the leapfrog's stability bound dt^2 lambda_max < 4
# with lambda_max bounded by the Gershgorin row k_rel
DT_LEAPFROG = 2.0
PACKING_FRACTION = {1: 1.0, 2: 0.85, 3: 0.64}


def packing_law(n, dim, d, form):
    """The law's radius, W at equilibrium and mean multiplier (see the module docstring)."""
    radius = 0.5 * d * (n / PACKING_FRACTION[dim]) ** (1.0 / dim)
    w_eq = n * dim / (2.0 * (dim + 2)) * radius * radius
    contacts = max(1.0, dim * n)
    lam_bar = w_eq / (contacts * d * d) if form == "S" else 2.0 * w_eq / (contacts * d)
    return {"radius": radius, "W": w_eq, "lam_bar": lam_bar, "g2": 4.0 * d * d if form == "S" else 1.0}


def scene_law(scene):
    """The law of a scene (a ``config.Scene``; see the module docstring): ``packing_law`` for
    the free cluster; the same in a container, where step 0 spreads a dense start uniformly over
    the container (``spread`` False: a ball about Xbar would cross the walls, and in the ball's
    place the explosion flung spheres through them: a 2D box of 200 discs was not certified in
    1e5 iterations, certified after 1250 with the fill); under gravity the bed's law.

    Gravity: the spheres settle into a bed of height H = N v / (phi_p A) (v the mean sphere's
    measure, A the container's floor) over its bottom h_0, so W_eq = g N m H / 2 (m the mean
    weight); the virial of a KKT point holds with W in place of the trap's (the floor carries
    the whole weight at h_0: sum_i m_i g (h_i - h_0) = sum_kl lambda_kl grad phi . r_kl), so that
    lam_bar has the same form; H stands for the radius in the explosion's cap and the fall."""
    law = packing_law(scene.n, scene.dim, scene.particles.d_mean, scene.method.form)
    if not scene.container.active:
        return law
    law["spread"] = False
    if scene.potential.kind != "gravity":
        return law
    n, dim, d = scene.n, scene.dim, scene.particles.d_mean
    ball = {1: 2.0, 2: math.pi, 3: 4.0 / 3.0 * math.pi}[dim]
    mean_power = scene.particles.mean_radius_power(dim)
    height = n * ball * mean_power / (PACKING_FRACTION[dim] * scene.container.section(dim))
    weight = mean_power / (0.5 * d) ** dim  # the mean of (d_i / d)^b
    w_eq = 0.5 * float(scene.potential.g) * n * weight * height
    contacts = max(1.0, dim * n)
    law.update(radius=height, W=w_eq,
               lam_bar=w_eq / (contacts * d * d) if scene.method.form == "S" else 2.0 * w_eq / (contacts * d))
    return law


class Phase(enum.StrEnum):
    """start -> explode -> fire, or start -> fire (the module docstring's steps 1 and 2-3)."""
    START = "start"
    EXPLODE = "explode"
    FIRE = "fire"


class Request(enum.StrEnum):
    """A change of the state the schedule asks for before the next pass."""
    EQUALISE = "equalise"          # spread the cloud into a uniform ball (step 0)
    FILL = "fill"                  # ... or uniformly over its container (step 0 in a container)
    RESET_LAMBDA = "reset_lambda"  # lambda := 0
    RESTART = "restart"            # momentum restart: X^{n-1} := X^n


class Coefficients(NamedTuple):
    """The fire-al kernel's coefficients of one pass (``kernels.fire``): the position update
    X^{n+1} = a1 X^n + a2 X^{n-1} - a3 grad W - a4 (penalty term), the dual gain beta, the
    multiplier floor, the clip form, the lambda-weighted dual and the speed cap vmax."""
    a1: float
    a2: float
    a3: float
    a4: float
    beta: float
    lam_floor: float
    clip: bool
    weighted_dual: bool
    vmax: float


@dataclasses.dataclass
class ScheduleState:
    """Everything the schedule decides from (and so everything a checkpoint carries of it)."""
    dt: float                      # FIRE's time step, its last and its bound
    dt_prev: float
    dt_max: float
    b: float                       # FIRE's last force coefficient (the kernel's a3)
    gain: float                    # T, the largest dual gain of a row (the explosion's beta)
    cb: float                      # the penalty factor c_b
    phase: Phase = Phase.START
    switch_iteration: int = 0      # the iteration that entered the fire phase
    pending: list = dataclasses.field(default_factory=list)  # Requests before the next pass
    spread: bool = False           # the start was spread into a ball (step 0)
    mix: float = MIX0              # FIRE's mixing, its positive-power count, |V| / (dt |G|)
    n_positive: int = 0
    speed_ratio: float = 0.0
    eta: float = ETA0              # the inner tolerance of the next multiplier step
    since_dual: int = 0            # iterations since the last multiplier step
    dual_now: bool = False         # the next pass is a multiplier step
    inner_residual: float = math.inf
    restarts: int = 0
    dual_steps: int = 0
    ov_dual: float = math.inf      # the max overlap at the last multiplier step
    qn: bool = False               # the inner solves are L-BFGS's, from iteration qn_from
    qn_from: int = 0
    w_mark: float = math.inf       # the quench: W at the last window's start (inf: none yet)


class FireALSchedule:
    """The schedule's state and decisions. Per iteration the method calls ``take_pending()``
    and ``coefficients()`` before the kernel pass and ``observe(fig)`` with the reduced
    figures after it."""

    # coefficients of a pass that moves nothing (compiling the kernel at set-up)
    NO_STEP = Coefficients(1.0, 0.0, 0.0, 0.0, 0.0, 0.0, False, False, 0.0)

    def __init__(self, n, dim, d, form, *, overlap_tol, law=None, jammed=False):
        law = law or packing_law(n, dim, d, form)
        # a jammed finish quenches (see QUENCH) where that pays
        self.quench = jammed and QUENCH[dim]
        # step 0, the spread into a ball about Xbar; in a container (law "spread" False), a
        # uniform fill of the container instead (a ball would cross its walls)
        self.spread = law.get("spread", True)
        # no forced multiplier step while the max overlap (relative to d_kl) is below this;
        # overlap_tol is the scene's stop.overlap
        self.hold_overlap = HOLD_OVERLAP * overlap_tol
        self.overlap_tol = overlap_tol
        self.d, self.dim, self.w_eq = d, dim, law["W"]
        self.cb_start, self.cb_grow = C_B[dim], CB_GROW[dim]
        # phi has the units of d^p (S: p = 2, NS: p = 1) and lambda those of W / d^p: the
        # penalty rho = c_b w / d_ij^p and the dual gains are per unit of phi / d_ij^p (each
        # pair's own size, in the kernel), and the explosion's a3 (the weight of grad W) is
        # gamma^2 d^p / 2, so that a scene scaled by any length is the same run
        self.phi_scale = d * d if form == "S" else d
        # the uniform ball of step 0, spread_factor law radii across (see JAMMED_SPREAD)
        self.spread_factor = JAMMED_SPREAD[dim] if jammed else SPREAD
        self.spread_radius = self.spread_factor * law["radius"]
        self.fall_iterations = int(2.0 * max(self.spread_factor - 1.0, 0.0) * law["radius"] / (VMAX * d))
        self.quench_max_inner = int(QUENCH_MAX_INNER * max(1.0, law["radius"] / (QUENCH_RADIUS * d)) ** 2)
        self.explode_cap = EXPLODE_CAP * law["radius"]
        self.lam_floor = FLOOR * law["lam_bar"]
        # the floor of a row's dual gain: |grad phi|^2 of one pair at distance d/2 (S: d^2; NS: 1)
        self.one_gain = d * d if form == "S" else 1.0
        s_law = KAPPA * law["g2"] * 2 * dim * law["lam_bar"]
        self.gamma_explode = math.sqrt(2.0 * THETA / s_law)
        k_rel = 1.0 + 2.0 * (4 * dim) * self.cb_start * self.lam_floor * law["g2"] / self.phi_scale
        dt_max = DT_LEAPFROG * math.sqrt(1.0 / k_rel)
        self.s = ScheduleState(dt=DT0_FRAC * dt_max, dt_prev=DT0_FRAC * dt_max, dt_max=dt_max,
                               b=(DT0_FRAC * dt_max) ** 2, gain=law["g2"] * 2 * dim, cb=self.cb_start)
        self.lbfgs = qn.LBFGS(qn.MEMORY[dim])

    @property
    def phase(self):
        return self.s.phase

    def quasi_newton_pass(self):
        """True when the next pass is an L-BFGS step (not a multiplier step, not FIRE's)."""
        return self.s.qn and not self.s.dual_now

    # ---- after an iteration ------------------------------------------------------------------
    def observe(self, fig):
        """Take the reduced figures of the iteration just done (kernel figures: max_gain,
        max_row, power, force2, change2, W, max_overlap)."""
        s = self.s
        if s.phase != Phase.FIRE:
            s.gain = max(fig["max_gain"], self.one_gain)  # at least one contact's
            if s.phase == Phase.START:
                s.phase = Phase.EXPLODE if fig["max_overlap"] > OV_START else Phase.FIRE
                if s.phase == Phase.EXPLODE and not self.spread:  # a dense start in a container
                    s.pending = [Request.FILL, Request.RESET_LAMBDA, Request.RESTART]
                    s.spread = True
                elif (s.phase == Phase.EXPLODE and self.spread_factor > 0
                      and fig["W"] < self.spread_factor ** 2 * self.w_eq):
                    s.pending = [Request.EQUALISE, Request.RESET_LAMBDA, Request.RESTART]
                    s.spread = True
            elif fig["max_overlap"] < OV_END or fig["W"] > W_SWITCH * self.w_eq:
                s.phase = Phase.FIRE
            if s.phase == Phase.FIRE:
                s.switch_iteration = fig["iteration"]
                s.pending = [Request.RESET_LAMBDA, Request.RESTART]
            return
        was_dual = s.dual_now
        # |grad W| = sqrt(2 W) for the centre and the point (W >= 0 up to rounding: N = 1 gives
        # W = -0.0...); gravity's is a constant of the scene, in the figures
        grad_w = math.sqrt(fig["grad_w2"] if "grad_w2" in fig else 2.0 * max(fig["W"], 0.0))
        s.since_dual += 1
        s.dual_now = False
        if s.qn:
            # an L-BFGS gradient pass has a3 = 1: force2 is |grad L_rho|^2 (a multiplier
            # step's pass moves nothing and says nothing about the inner solve)
            if not was_dual:
                grad = math.sqrt(fig["force2"])
                s.inner_residual = grad / grad_w if grad_w > 0 else math.inf
        else:
            self._fire_observe(fig, grad_w, was_dual)
        # forced after MAX_INNER iterations without one; the first one waits FIRST_INNER beyond
        # the fall from the spread ball (twice ~(SPREAD - 1) R / VMAX iterations at the speed
        # cap); none while the overlap is within the hold (only stationarity is missing)
        wait = MAX_INNER if s.dual_steps >= 1 else FIRST_INNER + self.fall_iterations
        if s.qn and fig["max_overlap"] > self.overlap_tol:
            wait = QN_MAX_INNER
        if self.quench:
            wait = min(wait, self.quench_max_inner if s.dual_steps >= 1 else self._quench_wait(fig))
        stalled = (MAX_INNER > 0 and s.since_dual >= wait
                   and fig["max_overlap"] > self.hold_overlap)
        if not was_dual and s.since_dual >= MIN_INNER and (s.inner_residual <= s.eta or stalled):
            s.dual_now = True
            s.dual_steps += 1
            if fig["max_overlap"] > PEN_GROW * s.ov_dual or self.quench:
                s.cb = min(self.cb_grow * s.cb, CB_MAX)
            s.ov_dual = fig["max_overlap"]
            s.since_dual = 0
            s.eta = max(ETA_MIN, s.eta * ETA_F)
            if s.qn:
                self.lbfgs.reset()  # the multipliers change L_rho: the memory is of another function
            elif s.cb >= QN_FROM_CB[self.dim]:
                # from the next inner solve on, L-BFGS; its first step a gradient step at the
                # stiffest row's scale (k_rel bounds Hess L_rho's largest eigenvalue)
                s.qn = True
                s.qn_from = fig["iteration"] + 1
                k_rel = max(fig["max_row"] / s.b, 1.0)
                self.lbfgs = qn.LBFGS(qn.MEMORY[self.dim], h0=1.0 / k_rel)

    def _quench_wait(self, fig):
        """The quench's wait for the first multiplier step: 0 (now) when W has settled over the
        last QUENCH_WINDOW iterations of the fire phase, else no forced step before the usual
        FIRST_INNER beyond the fall. W is compared every QUENCH_WINDOW iterations."""
        s = self.s
        if (fig["iteration"] - s.switch_iteration) % QUENCH_WINDOW != 0:
            return math.inf
        mark, s.w_mark = s.w_mark, fig["W"]
        if abs(fig["W"] - mark) <= QUENCH_SETTLED * abs(fig["W"]):  # False while mark is inf
            return 0
        return math.inf

    def _fire_observe(self, fig, grad_w, was_dual):
        """FIRE's part of ``observe``: the inner residual, restarts, dt and the mixing."""
        s = self.s
        b_prev = s.b
        k_rel = max(fig["max_row"] / b_prev, 1.0)
        s.dt_max = DT_LEAPFROG * math.sqrt(1.0 / k_rel)
        grad = math.sqrt(fig["force2"]) / b_prev  # ||grad L_rho||
        s.inner_residual = grad / grad_w if grad_w > 0 else math.inf
        s.speed_ratio = math.sqrt(fig["change2"]) / (s.dt * grad) if grad > 0 else 0.0
        if fig["power"] < 0 and not was_dual:
            s.pending = [Request.RESTART]
            s.restarts += 1
            s.dt *= F_DEC
            s.mix = MIX0
            s.n_positive = 0
        else:
            s.n_positive += 1
            if s.n_positive > N_DELAY:
                s.dt = min(s.dt * F_INC, s.dt_max)
                s.mix *= F_MIX
        s.dt = min(s.dt, s.dt_max)

    # ---- before an iteration -----------------------------------------------------------------
    def take_pending(self):
        """The state changes due before the next pass (and forget them)."""
        todo, self.s.pending = self.s.pending, []
        return todo

    def coefficients(self):
        """The ``Coefficients`` of the next pass."""
        s = self.s
        if s.phase != Phase.FIRE:
            a4 = 0.5 * self.gamma_explode ** 2  # DAHA, c = 2, alpha = gamma (in units of d)
            a3 = a4 * self.phi_scale
            q = (Q_GENTLE if s.spread else Q_EXPLODE) if s.phase == Phase.EXPLODE else 0.5
            return Coefficients(1.0, 0.0, a3, a4, q / (a3 * s.gain), 0.0, False, False, self.explode_cap)
        cb = s.cb
        if s.qn:
            if s.dual_now:  # the (damped) multiplier step alone: a3 = 0 moves nothing
                return Coefficients(1.0, 0.0, 0.0, 0.0, QN_DUAL_STEP[self.dim] * cb, self.lam_floor, True, True, 0.0)
            # L-BFGS's gradient pass: x_new = X^n - grad L_rho (``kernels_qn``)
            return Coefficients(1.0, 0.0, 1.0, cb, 0.0, self.lam_floor, True, True, 0.0)
        dt, mix = s.dt, s.mix
        a = (1.0 - mix) * dt / s.dt_prev
        b = (1.0 - mix) * dt * dt + mix * dt * dt * s.speed_ratio
        s.dt_prev, s.b = dt, b
        # rho = c_b max(lambda, lam_fl) per unit of phi / d_ij^p (the kernel divides)
        if s.dual_now:  # the multiplier step: lambda + rho phi, penalty off
            a4, beta = 0.0, cb
        else:
            a4, beta = b * cb, (OMEGA * cb if cb == self.cb_start else 0.0)
        return Coefficients(1.0 + a, -a, b, a4, beta, self.lam_floor, True, True, VMAX * self.d)

    def force_multiplier(self):
        """(pen, lam_floor) of the force multipliers mu = max(0, lambda + pen max(lambda,
        lam_floor) phi / d_ij^p) that the next pass moves the spheres with (the certificate's
        multipliers): the augmented Lagrangian's first-order estimate."""
        return self.s.cb, self.lam_floor

    # ---- checkpoint ----------------------------------------------------------------------------
    def save(self):
        """The state as a JSON-able dict (the checkpoint's "schedule")."""
        out = dataclasses.asdict(self.s)
        out["phase"], out["pending"] = str(self.s.phase), [str(r) for r in self.s.pending]
        out["lbfgs"] = self.lbfgs.save()
        return out

    def restore(self, saved):
        saved = dict(saved)
        lbfgs = saved.pop("lbfgs", None)
        known = {f.name for f in dataclasses.fields(ScheduleState)}
        self.s = dataclasses.replace(self.s, **{k: v for k, v in saved.items() if k in known})
        self.s.phase = Phase(self.s.phase)
        self.s.pending = [Request(r) for r in saved.get("pending", [])]
        if lbfgs is not None:
            self.lbfgs.restore(lbfgs)

    def summary(self):
        s = self.s
        return {"phase": str(s.phase), "switch_iteration": s.switch_iteration,
                "spread": bool(s.spread), "restarts": s.restarts, "dual_steps": s.dual_steps,
                "penalty_factor": s.cb,
                "lbfgs_from": s.qn_from if s.qn else None,
                "lbfgs_resets": self.lbfgs.s["resets"] if s.qn else 0,
                "lbfgs_rejected": self.lbfgs.s["rejected"] if s.qn else 0,
                "lbfgs_shortened": self.lbfgs.s["clipped"] if s.qn else 0}
