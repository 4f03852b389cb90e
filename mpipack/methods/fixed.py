"""DAHA (2.10) and AHA (2.8) with the scene's fixed parameters (alpha, beta, gamma, c): the
paper's methods as given. One kernel pass per iteration:

    lambda^n   = max(0, lambda^{n-1} + beta phi(X^n))                                 (2.10b)
    X^{n+1}    = a1 X^n + a2 X^{n-1} - a3 grad W(X^n) - a4 sum lambda^n grad phi ...  (2.10a)

with (a1, a2, a3, a4) from (alpha, gamma, c) (``PaperCoefficients``; AHA: c = 0 damping-free,
gamma = 0). Their stability depends on the parameters: ``mpipack check`` gives the range.
"""

from typing import NamedTuple

from mpipack.kernels import daha as kernels
from mpipack.methods.base import PaperScheme


class PaperCoefficients(NamedTuple):
    """The position update's coefficients, X^{n+1} = a1 X^n + a2 X^{n-1} - a3 (X^n - Xbar)
    - a4 (the multiplier and gamma terms) (``kernels.daha``)."""
    a1: float
    a2: float
    a3: float
    a4: float


def paper_coefficients(method, alpha, beta, gamma, c):
    """(a1, a2, a3, a4) of the position update for 'daha' (2.10a), with h = 1 + c/2:
    2/h, -(1 - c/2)/h, alpha^2/h, gamma^2/h; or 'aha' (2.8a): 1, 0, alpha, 0."""
    if method == "daha":
        h = 1.0 + 0.5 * c
        return PaperCoefficients(2.0 / h, -(1.0 - 0.5 * c) / h, alpha * alpha / h, gamma * gamma / h)
    if method == "aha":
        return PaperCoefficients(1.0, 0.0, alpha, 0.0)
    raise ValueError(f"no one-pass kernel for method {method!r}")


class FixedStep(PaperScheme):
    """DAHA or AHA with fixed parameters (``method.schedule = "fixed"``)."""

    def __init__(self, scene):
        m = scene.method
        self.name, self.dim = m.name, scene.dim
        self.gravity = scene.potential.kind == "gravity"
        self.beta = float(m.beta)
        self.coeffs = paper_coefficients(m.name, m.alpha, m.beta, m.gamma, m.c)
        self.kernel = kernels.multipliers_and_step(m.form, scene.dim)

    def iterate(self, solver):
        fig = solver.advance(solver.state.x_prev, solver.xbar)  # (2.10b) then (2.10a)
        return solver.end_iteration(fig)

    def advice(self):
        if self.name == "aha":
            return 'AHA has no damping: use method.name = "daha", or lower method.beta or method.alpha'
        return ("`mpipack check SCENE` gives the stable range of the parameters (usually: raise method.c, "
                "lower method.beta or method.alpha); or leave method.alpha, beta, gamma and c unset for "
                "the fire-al schedule (docs/user-guide.md)")
