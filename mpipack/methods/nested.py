"""The nested methods, NAP (2.16) and NAV (2.17): an outer iteration p -> p+1 runs inner
iterations with the constraints linearised about the outer iterate X^p (2.15), held in
``state.x_lin``, then updates the multipliers from the last inner iterate.

Each inner iteration is one ``Solver.advance`` (kernel, reduction, fresh ghosts).
"""

import math
from typing import NamedTuple

import numpy as np

from mpipack.kernels import daha as kernels
from mpipack.methods.base import PaperScheme
from mpipack.parallel import neighbors
from mpipack.parallel.reduction import Reduction


class NestedCoefficients(NamedTuple):
    """The inner update's coefficients (``kernels.daha._nested_step``): Y^{n+1} = cy Y^n
    + cp X^p - cw (grad W) - cf (the linearised multiplier term)."""
    cy: float
    cp: float
    cw: float
    cf: float


def nested_coefficients(method, alpha, tau):
    """(cy, cp, cw, cf) of the inner update: NAP (2.16a) 1, 0, alpha, alpha; NAV (2.17a)
    1 - alpha, alpha, alpha tau, alpha tau^2."""
    if method == "nap":
        return NestedCoefficients(1.0, 0.0, alpha, alpha)
    if method == "nav":
        return NestedCoefficients(1.0 - alpha, alpha, alpha * tau, alpha * tau * tau)
    raise ValueError(f"not a nested method: {method!r}")


class Nested(PaperScheme):
    """NAP or NAV (``method.name``), with method.l_inner inner steps at most and the inner
    criterion method.eps_inner."""

    extra_fields = ("x_lin",)
    counts_inner = True
    skin_free = False

    def __init__(self, scene):
        m = scene.method
        self.name, self.dim, self.n = m.name, scene.dim, scene.n
        self.l_inner, self.eps_inner = int(m.l_inner), m.eps_inner
        self.beta = float(m.beta)
        self.gravity = scene.potential.kind == "gravity"
        self.centre = scene.potential.kind == "centre"
        self.coeffs = nested_coefficients(m.name, m.alpha, m.tau)
        # the container's walls and the potential as the DAHA kernels take them
        self.kernel = kernels.nested_step(m.name, m.form)
        # the multipliers of the KKT system (2.4) are NAV's times tau (its solve (2.6))
        self.kkt_lambda_scale = float(m.tau) if m.name == "nav" else 1.0

    def iterate(self, s):
        """One outer iteration p -> p+1 of NAP (2.16) or NAV (2.17).

        The constraints are linearised about X^p (kept in x_lin, ghosts included, and carried
        through rebuilds). Inner steps run until the inner criterion, (4.1) for NAP:
        ||X^{p,n+1} - X^{p,n}|| / ||X^{p,n}|| < eps_inner, (4.2) for NAV:
        ||V^{p,n+1} - V^{p,n}|| / ||X^p|| < eps_inner / tau, or l_inner steps. Then
        lambda^{p+1} from the last inner iterate, and the outer criterion (4.3) is measured.
        NAV's inner variable is Y = X^p + tau V; it starts from V^{p,0} = V^p, i.e.
        Y = X^p + (X^p - X^{p-1}) (V^0 = 0).
        """
        st = s.state
        n = st.n_local
        st.x_lin[:] = st.x  # X^p, ghosts are current
        if not self.centre:  # W^p of the point potential or gravity, from exact sums of X^p
            _, w_p = s.centre_of_mass()
        nav = self.name == "nav"
        xbar_p = s.xbar.copy()
        if nav:
            red = Reduction().add_exact("sums", [("x", self.dim), ("xx", 1)]).begin()
            kernels.local_sums(st.x, n, red.acc("sums"))
            norm_p = math.sqrt(red.reduce(s.comm).value("xx"))  # ||X^p||, for (4.2)
            st.x[:n] = 2.0 * st.x_lin[:n] - st.x_prev[:n]
            # the warm start moves every particle by |X^p - X^{p-1}|: it counts for the rows
            jump2 = neighbors.max_displacement2(st.x, st.x_lin, n)
            s.refresh_ghosts(math.sqrt(s.comm.allreduce(np.array([jump2]), op="max")[0]))
            if s.point is not None:
                s.sum_x = None  # sum X^p, not of the warm start: the first pass sums it again
        inner = 0
        fig = {}
        for inner in range(1, self.l_inner + 1):
            fig = s.advance(st.x_lin, xbar_p if nav else s.xbar)
            s.xbar = fig.pop("xbar")
            if nav:
                rel_inner = math.sqrt(fig["change2"]) / norm_p if norm_p > 0 else 0.0
            else:
                rel_inner = fig["relative_change"]
            if rel_inner < self.eps_inner:
                break
        s.counters["inner_iterations"] += inner
        # (2.16b) / (2.17b) for the last inner iterate: lambda^{p+1}; positions are discarded
        scratch = Reduction().add_exact("step", self.step_sums()) \
            .add_max("step", self.step_maxima()).begin()
        self.kernel_pass(s, st.x_lin, s.xbar, scratch)
        st.lambda_fresh = True
        # outer criterion (4.3): ||X^{p+1} - X^p|| / ||X^p||
        red = Reduction().add_exact("change", [("d2", 1), ("p2", 1)]).begin()
        kernels.change_sums(st.x, st.x_lin, st.n_local, red.acc("change"))
        red.reduce(s.comm)
        d2, p2 = red.value("d2"), red.value("p2")
        st.x_prev[:st.n_local] = st.x_lin[:st.n_local]  # X^{p}, for NAV's V^{p+1}
        st.iteration += 1
        fig["relative_change"] = math.sqrt(d2 / p2) if p2 > 0 else (0.0 if d2 == 0 else math.inf)
        # W^p, as DAHA's figures carry W^n
        fig["W"] = 0.5 * (p2 - self.n * float(xbar_p @ xbar_p)) if self.centre else w_p
        fig["iteration"] = st.iteration
        fig["inner_iterations"] = inner
        return fig

    def advice(self):
        return "lower method.alpha or method.tau, or raise method.l_inner"
