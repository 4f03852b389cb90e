"""The outer iteration of the nested methods, NAP (2.16) and NAV (2.17), on a ``Solver``.

Each inner iteration is one ``Solver._advance`` (kernel, reduction, fresh ghosts), with the
constraints linearised about the outer iterate X^p (2.15), held in ``state.x_lin``.
"""

import math

import numpy as np

from mpipack.kernels import daha as kernels
from mpipack.parallel import neighbors
from mpipack.parallel.reduction import Reduction


def outer_step(s):
    """One outer iteration p -> p+1 of NAP (2.16) or NAV (2.17).

    The constraints are linearised about X^p (kept in x_lin, ghosts included, and carried
    through rebuilds). Inner steps run until the inner criterion, (4.1) for NAP:
    ||X^{p,n+1} - X^{p,n}|| / ||X^{p,n}|| < eps_inner, (4.2) for NAV:
    ||V^{p,n+1} - V^{p,n}|| / ||X^p|| < eps_inner / tau, or l_inner steps. Then
    lambda^{p+1} from the last inner iterate, and the outer criterion (4.3) is measured.
    NAV's inner variable is Y = X^p + tau V; it starts from V^{p,0} = V^p, i.e.
    Y = X^p + (X^p - X^{p-1}) (V^0 = 0).
    """
    st, m = s.state, s.params
    n = st.n_local
    st.x_lin[:] = st.x  # X^p, ghosts are current
    nav = m.name == "nav"
    xbar_p = s.xbar.copy()
    if nav:
        red = Reduction().add_exact("sums", [("x", s.dim), ("xx", 1)]).begin()
        kernels.local_sums(st.x, n, red.acc("sums"))
        norm_p = math.sqrt(red.reduce(s.comm).value("xx"))  # ||X^p||, for (4.2)
        st.x[:n] = 2.0 * st.x_lin[:n] - st.x_prev[:n]
        # the warm start moves every particle by |X^p - X^{p-1}|: it counts for the rows
        jump2 = neighbors.max_displacement2(st.x, st.x_lin, n)
        s._refresh_ghosts(math.sqrt(s.comm.allreduce(np.array([jump2]), op="max")[0]))
    inner = 0
    fig = {}
    for inner in range(1, int(m.l_inner) + 1):
        fig = s._advance(st.x_lin, xbar_p if nav else s.xbar)
        s.xbar = fig.pop("xbar")
        if nav:
            rel_inner = math.sqrt(fig["change2"]) / norm_p if norm_p > 0 else 0.0
        else:
            rel_inner = fig["relative_change"]
        if rel_inner < m.eps_inner:
            break
    s.counters["inner_iterations"] += inner
    # (2.16b) / (2.17b) for the last inner iterate: lambda^{p+1}; positions are discarded
    scratch = Reduction().add_exact("step", [("x", s.dim), ("dx2", 1), ("xx2", 1)]) \
        .add_max("step", [("step2", 1), ("overlap", 1)]).begin()
    s._kernel(st.x, st.x_lin, st.x_new, st.n_local, st.diam, st.pair_offsets, st.pair_j,
                 st.pair_lambda, s.xbar, *s.coeffs, s.beta, not st.lambda_fresh,
                 scratch.acc("step"), scratch.maxima("step"))
    st.lambda_fresh = True
    # outer criterion (4.3): ||X^{p+1} - X^p|| / ||X^p||
    red = Reduction().add_exact("change", [("d2", 1), ("p2", 1)]).begin()
    kernels.change_sums(st.x, st.x_lin, st.n_local, red.acc("change"))
    red.reduce(s.comm)
    d2, p2 = red.value("d2"), red.value("p2")
    st.x_prev[:st.n_local] = st.x_lin[:st.n_local]  # X^{p}, for NAV's V^{p+1}
    st.iteration += 1
    fig["relative_change"] = math.sqrt(d2 / p2) if p2 > 0 else (0.0 if d2 == 0 else math.inf)
    fig["W"] = 0.5 * (p2 - s.n * float(xbar_p @ xbar_p))  # W^p, as DAHA's figures carry W^n
    fig["iteration"] = st.iteration
    fig["inner_iterations"] = inner
    return fig
