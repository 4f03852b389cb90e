"""The scalar side of a distributed L-BFGS ("vector-free" form): no MPI, no particle arrays.

Every sphere keeps, in ``State.qn`` (n_local, 2m + 1, b), its pieces of

    S_0 .. S_{m-1}   the last m steps s = X^{k+1} - X^k        (a ring: ``head`` is the newest)
    Y_0 .. Y_{m-1}   their gradient changes y = g^{k+1} - g^k
    G_OLD            the gradient of the previous iterate

(g = grad L_rho, the inner problem's gradient; the current one is the gradient pass's output,
read where it lies). The two-loop recursion of L-BFGS (Nocedal and Wright, Algorithm 7.4)
needs only dot products of these vectors, so it runs here on their Gram matrix B over the basis

    [S_0 .. S_{m-1}, Y_0 .. Y_{m-1}, g]        (indices 0 .. 2m)

(Chen, Wang and Zhou, "Large-scale L-BFGS using MapReduce", NIPS 2014): the direction p = -H g
comes out as coefficients c over the basis, p_i = sum_j c_j basis_j(i), applied sphere by
sphere (``kernels_qn.direction``).

Per iteration the kernels give the exact sums g.S_j, g.Y_j, g.G_OLD and g.g of the new gradient
(``kernels_qn.dots``: 2m + 2 numbers, the same on every rank); every other entry of B follows
from B's previous entries: the step just taken is s = sum c_j b_j, so s.b = sum c_j B_j.b, and
y = g - g_old, so y.b = g.b - g_old.b. The result is the same on any number of ranks because
its inputs are.

A step is accepted when L_rho fell enough by the trapezoid estimate
L(X + s) - L(X) ~ (g_old + g).s / 2 (exact for a quadratic), i.e. (g_old + g).s / 2 <= ARMIJO
g_old.s. A step that fails is halved (X := X - s/2, the memory kept: a backtracking line
search, one gradient per trial), up to MAX_BACKTRACK times; then, or when a pair (s, y) has no
positive curvature s.y > 0, the memory is dropped and the next step is a scaled gradient step.
"""

import numpy as np

# pairs (s, y) kept, by dimension: the memory costs (2m + 1) b 8 bytes per sphere (m = 5: 176
# bytes in 2D, 264 in 3D). m = 2 in 3D (120 bytes) certified 3D N = 2000 seeds 0 - 9 in 13% more
# iterations than m = 5 (docs/research/convergence.md, section 3q)
MEMORY = {1: 5, 2: 5, 3: 5}
ARMIJO = 1e-4
MAX_BACKTRACK = 4
# the largest move of a sphere in one step, in units of d: a longer one is shortened (and the
# memory dropped), as FIRE's speed cap does
TRUST = 0.05


def overshot(slope_old, slope_new):
    """The trapezoid test of a step s: True when L_rho did not fall enough, (g_old.s + g.s) / 2
    > ARMIJO g_old.s (slope_old = g_old.s where the step began, slope_new = g.s where it ended)."""
    return 0.5 * (slope_old + slope_new) > ARMIJO * slope_old


def slots(m):
    """Per-sphere vectors kept: S (m), Y (m), G_OLD."""
    return 2 * m + 1


class LBFGS:
    """The memory's scalars and the two-loop recursion on the Gram matrix."""

    def __init__(self, m=5, h0=1.0):
        self.m = m
        self.s = {"k": 0, "head": m - 1, "stepped": False, "h0": float(h0), "h0_max": np.inf,
                  "resets": 0, "rejected": 0, "backtracks": 0, "clipped": 0, "curvature": 0}
        self.B = np.zeros((2 * m + 1, 2 * m + 1))

    # ---- state -----------------------------------------------------------------------------
    def reset(self):
        """Forget the pairs (the inner problem changed, or a step failed); keep the scale."""
        self.s["k"] = 0
        self.s["stepped"] = False
        self.s["resets"] += 1

    def save(self):
        out = dict(self.s)
        out["m"], out["B"] = self.m, self.B.tolist()
        return out

    def restore(self, saved):
        saved = dict(saved)
        self.m = int(saved.pop("m", self.m))
        self.B = np.array(saved.pop("B"), dtype=np.float64)
        self.s.update(saved)

    # ---- one iteration ---------------------------------------------------------------------
    def direction(self, dots, slope, clipped=False):
        """The next step from the new gradient's exact dots (length 2m + 2: g.S_j, g.Y_j,
        g.G_OLD, g.g). Returns (coef, y_slot, s_slot, accepted):

        coef (2m + 1,) over the basis [S, Y, g]: X^{n+1} = X^n + sum_j coef_j basis_j; y_slot
        the slot that receives g - g_old (-1: none); s_slot the slot that receives the step.
        coef None: a backtrack, the last step (slot s_slot) is halved and undone by half
        (``kernels_qn.backtrack``). ``clipped``: some sphere's last step was shortened
        (``kernels_qn.direction``), so that the stored step is not the one B holds: the memory
        is dropped, and ``slope`` (g_old.s of the step as taken, an exact sum of
        ``kernels_qn.dots``; unused for a step that was not shortened, whose g_old.s B holds)
        with g.s (dots) decides whether it descended. One that did not
        halves the gradient scale h0: a gradient step that the trust region shortens and that
        overshoots anyway (a sphere flung into a stiff contact and back) would otherwise repeat
        forever, never tested (two spheres in 3D: a 2-cycle between a gap of 2.7e-3 d and an
        overlap of 0.097 d). The scale so halved also bounds the scale s.y / y.y that later
        pairs give (``h0_max``): a pair taken where no contact is touched learns W's curvature
        alone, 1, and its next step would overshoot into the contact again."""
        m, s, B = self.m, self.s, self.B
        G = 2 * m  # the gradient's index in the basis
        gg = float(dots[2 * m + 1])
        accepted = True
        y_slot = -1
        if s["stepped"] and clipped:
            accepted = False
            s["clipped"] += 1
            if overshot(slope, float(dots[s["head"]])):
                s["rejected"] += 1
                s["h0"] *= 0.5
                s["h0_max"] = s["h0"]
        elif s["stepped"]:
            h = s["head"]
            g_s = float(dots[h])  # g.s of the step just taken (an exact sum of the kernel)
            go_s = float(B[h, G])  # g_old.s, filled when the step was taken
            if overshot(go_s, g_s):
                s["rejected"] += 1
                if s["backtracks"] < MAX_BACKTRACK:
                    s["backtracks"] += 1
                    # the step from the same X is now s/2: its row of B halves (s.s quarters)
                    B[h, :] *= 0.5
                    B[:, h] *= 0.5
                    return None, -1, h, False
                accepted = False
                s["h0"] *= 0.5
            else:
                # y = g - g_old against every basis vector (S_h is already the new step);
                # B[G] is still g_old's row
                y_row = dots[:2 * m + 1] - B[G]
                yy = gg - 2.0 * float(dots[2 * m]) + float(B[G, G])
                sy = float(y_row[h])
                if sy > 0.0 and yy > 0.0:
                    y_row[m + h] = yy
                    B[m + h, :] = y_row
                    B[:, m + h] = y_row
                    s["k"] = min(s["k"] + 1, m)
                    s["h0"] = min(sy / yy, s["h0_max"])
                    s["h0_max"] *= 2.0  # a bound that held widens again (inf stays inf)
                    y_slot = h
                else:
                    accepted = False
                    s["curvature"] += 1
        s["backtracks"] = 0
        if not accepted:
            self.reset()
        # the new gradient's row (its entry against Y_h: g.y = g.g - g.g_old)
        row = np.array(dots[:2 * m + 1], dtype=np.float64)
        if y_slot >= 0:
            row[m + y_slot] = gg - float(dots[2 * m])
        row[G] = gg
        B[G, :] = row
        B[:, G] = row
        # the two-loop recursion on coefficients over the basis, q = g
        k, h = s["k"], s["head"]
        pairs = [(h - i) % m for i in range(k)]  # newest first
        q = np.zeros(2 * m + 1)
        q[G] = 1.0
        alpha = []
        for j in pairs:
            a = float(B[j] @ q) / B[j, m + j]
            q[m + j] -= a
            alpha.append(a)
        q *= s["h0"]
        for j, a in zip(reversed(pairs), reversed(alpha)):
            b = float(B[m + j] @ q) / B[j, m + j]
            q[j] += a - b
        c = -q
        if not float(c @ B[G]) < 0.0:  # not a descent direction: a gradient step
            self.reset()
            c = np.zeros(2 * m + 1)
            c[G] = -s["h0"]
        # the new step s = p in the slot after head: its row of B against the basis (computed
        # before the slot is overwritten: p may use the vector it replaces)
        new = (h + 1) % m
        s_row = B @ c
        s_row[new] = float(c @ B @ c)
        s_row[m + new] = 0.0  # that slot's Y is stale (it leaves the memory next)
        B[new, :] = s_row
        B[:, new] = s_row
        if s["k"] == m:
            s["k"] = m - 1  # the oldest pair was in this slot
        s["head"] = new
        s["stepped"] = True
        return c, y_slot, new, accepted
