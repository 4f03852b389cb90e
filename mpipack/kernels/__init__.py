"""The kernels: ``@njit`` array functions over one rank's arrays, numba only. They never import
mpi4py (nor any module that does): a kernel fills exact-sum accumulators and maxima that the
engine reduces. ``daha``: the paper's steps (DAHA/AHA (2.10), NAP/NAV (2.16)-(2.17)), the
shared sphere/pair helpers and the metrics pass; ``fire``: the fire-al schedule's augmented
Lagrangian step; ``lbfgs``: the per-sphere side of L-BFGS; ``fit``: the best multipliers'
projected gradient; ``metrics``: covered measure (density)."""
