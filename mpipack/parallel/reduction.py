"""The per-iteration reduction as named fields: exact sums, integer counts and maxima that travel
in ONE allreduce. No physics here, and no MPI either (``comm.reduce_fused`` moves the buffers).

A field is registered once, by name, before the first reduction:

    exact   rows of order-independent float sums (``exactsum`` accumulators, int64 bins)
    count   an int64 sum
    max     float64 values >= 0 (NaN wins: a NaN anywhere is seen everywhere)

A kernel that fills several fields at once gets a *block*: consecutive rows it writes through
one array view (``acc(block)`` / ``maxima(block)``), so the numba signatures stay plain
arrays. Whoever owns a value that is not produced by a kernel (the loop's wall clock, a stop
request from a signal) registers it with ``fill``: a callable run just before every reduction.

Layout of the two buffers (the order of registration):

    sums    int64  [exact block 0 rows x (NBINS+1) | exact block 1 ... | count 0 | count 1 ...]
    maxima  float64 [max block 0 | max block 1 ...]

Readers use names: ``value("dx2")``, ``values("x")`` (all rows of a field), ``count("active")``,
``max("overlap")``. All ranks read the same numbers, so every decision taken from them is
collective.
"""

import numpy as np

from mpipack.jit import njit
from mpipack.parallel import exactsum

_ROW = exactsum.NBINS + 1


class Reduction:
    def __init__(self):
        self._exact = {}  # field -> (first row, rows)
        self._exact_blocks = {}  # block -> (first row, rows)
        self._counts = {}  # field -> index among the counts
        self._max = {}  # field -> (first index, rows)
        self._max_blocks = {}
        self._fills = []
        self._n_exact_rows = 0
        self._n_max = 0
        self.sums = None
        self.maxima_buf = None
        self.global_sums = None
        self.global_maxima = None
        self._values = None
        self._overflowed, self._maxima_finite = False, True

    # ---- registration -----------------------------------------------------------------
    def add_exact(self, block, fields):
        """Register an exact block: ``fields`` is a list of (name, rows)."""
        self._check_open(block, self._exact_blocks, [f for f, _ in fields], self._exact)
        start = self._n_exact_rows
        for name, rows in fields:
            self._exact[name] = (self._n_exact_rows, rows)
            self._n_exact_rows += rows
        self._exact_blocks[block] = (start, self._n_exact_rows - start)
        return self

    def add_count(self, name, fill=None):
        self._check_open(name, self._counts, [], {})
        self._counts[name] = len(self._counts)
        if fill is not None:
            self._fills.append(("count", name, fill))
        return self

    def add_max(self, block, fields, fill=None):
        """Register a block of maxima: ``fields`` is a list of (name, rows). With ``fill``, a
        callable returning the block's local values, called before every reduction."""
        self._check_open(block, self._max_blocks, [f for f, _ in fields], self._max)
        start = self._n_max
        for name, rows in fields:
            self._max[name] = (self._n_max, rows)
            self._n_max += rows
        self._max_blocks[block] = (start, self._n_max - start)
        if fill is not None:
            self._fills.append(("max", block, fill))
        return self

    def _check_open(self, block, blocks, fields, registered):
        """Names are unique per kind (an exact block and a max block may share a name)."""
        if self.sums is not None:
            raise RuntimeError(f"reduction field {block!r} added after the buffers were made")
        for name in [block] * (block in blocks) + [f for f in fields if f in registered]:
            raise ValueError(f"reduction field {name!r} registered twice")

    def _allocate(self):
        self.sums = np.zeros(self._n_exact_rows * _ROW + len(self._counts), dtype=np.int64)
        self.maxima_buf = np.zeros(self._n_max)

    # ---- local side ---------------------------------------------------------------------
    def begin(self):
        """Zero the local sums (maxima are overwritten by their owners). Returns self."""
        if self.sums is None:
            self._allocate()
        self.sums[:] = 0
        return self

    def acc(self, block):
        """int64 view (rows, NBINS+1) of an exact block's local accumulator."""
        first, rows = self._exact_blocks[block]
        return self.sums[first * _ROW:(first + rows) * _ROW].reshape(rows, _ROW)

    def maxima(self, block):
        """float64 view of a max block's local values."""
        first, rows = self._max_blocks[block]
        return self.maxima_buf[first:first + rows]

    def set_count(self, name, value):
        self.sums[self._n_exact_rows * _ROW + self._counts[name]] = value

    def set_max(self, name, value):
        first, _ = self._max[name]
        self.maxima_buf[first] = value

    # ---- the reduction --------------------------------------------------------------------
    def reduce(self, comm):
        """Run the fills, then one allreduce; the global values are then readable by name."""
        if self.sums is None:
            self._allocate()
        for kind, name, fill in self._fills:
            if kind == "count":
                self.set_count(name, fill())
            else:
                self.maxima(name)[:] = fill()
        self.global_sums, self.global_maxima = comm.reduce_fused(self.sums, self.maxima_buf)
        n = self._n_exact_rows
        # every reader needs them (the solver's finiteness check, first): one compiled call
        self._values, self._overflowed, self._maxima_finite = _read_global(
            self.global_sums[:n * _ROW].reshape(n, _ROW), self.global_maxima)
        return self

    # ---- global side ----------------------------------------------------------------------
    def value(self, name, row=0):
        """float64 value of an exact field (row ``row``); NaN if any rank overflowed it."""
        first, rows = self._exact[name]
        if not 0 <= row < rows:
            raise IndexError(f"exact field {name!r} has {rows} rows, not row {row}")
        return float(self._values[first + row])

    def values(self, name):
        first, rows = self._exact[name]
        return self._values[first:first + rows].copy()

    def overflowed(self):
        """True when some exact sum met a NaN, Inf or a value beyond exactsum.RANGE (its value
        is then NaN: a finite value is never NaN)."""
        return self._overflowed

    def count(self, name):
        return int(self.global_sums[self._n_exact_rows * _ROW + self._counts[name]])

    def max(self, name, row=0):
        first, _ = self._max[name]
        return float(self.global_maxima[first + row])

    def all_maxima_finite(self):
        return self._maxima_finite


@njit(cache=True)
def _read_global(exact_rows, maxima):
    """The reduced buffers read once: (values (rows,) of the exact rows, NaN where a rank
    overflowed; whether any did; whether every maximum is finite)."""
    values = exactsum.values_all(exact_rows)
    overflowed = False
    for v in values:
        if np.isnan(v):
            overflowed = True
    finite = True
    for m in maxima:
        if not np.isfinite(m):
            finite = False
    return values, overflowed, finite
