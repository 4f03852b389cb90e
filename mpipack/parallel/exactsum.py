"""Order-independent ("exact") sums of float64 values, for rank-count-independent reductions.

A floating-point sum depends on the order of its terms, and the order depends on how the
particles are split across ranks. Here every term is first cut, deterministically and
independently of the others, into four pieces that are integer multiples of fixed powers of
two ("bins", as in ReproBLAS' indexed sums); the pieces of one bin are then added exactly.
Sums of integers are associative, so the result is the same for any order and any partition.

Value x is split with the "add a big constant" trick, which is exact in IEEE round-to-nearest
arithmetic without fastmath (no reassociation):

    q_k = (r_k + M_k) - M_k,   r_{k+1} = r_k - q_k,   M_k = 1.5 * 2**E_k,

so q_k is r_k rounded to a multiple of ulp(M_k) = 2**(E_k - 52). The bins are 41 bits apart,
which leaves 12 bits of headroom: up to FLUSH_EVERY pieces add exactly in a float64
accumulator before it is flushed into int64 counters (units of ulp(M_k)) and carried.

Range and resolution: |x| < RANGE = 2**85 (about 3.9e25; so positions up to about 6e12 when
their squares are summed) is summed; the part of x below 2**-78 (about 3e-24) is dropped,
deterministically. A value outside the range, or NaN/Inf, marks the accumulator as
overflowed, which the solver reports as numerical trouble.

The accumulator is a small int64 array ``acc[n_quantities, NBINS + 1]``: NBINS counters and one
overflow flag per quantity. Accumulators from several ranks combine by integer addition
(``MPI.SUM`` on int64); ``value`` turns one back into a float64, identically on every rank.
"""

import numpy as np

from mpipack.jit import float_bits, njit

NBINS = 4
_E0 = 97
_BIN_GAP = 41
_EXPS = np.array([_E0 - _BIN_GAP * k for k in range(NBINS)], dtype=np.int64)
_M = np.array([1.5 * 2.0 ** int(e) for e in _EXPS])
_ULP = np.array([2.0 ** int(e - 52) for e in _EXPS])
RANGE = 2.0 ** (_E0 - 12)
FLUSH_EVERY = 2048

M0, M1, M2, M3 = (float(v) for v in _M)
ULP0, ULP1, ULP2, ULP3 = (float(v) for v in _ULP)
_CARRY = np.int64(_BIN_GAP)


def new_accumulator(n_quantities):
    """Zeroed accumulator, shape (n_quantities, NBINS + 1), int64."""
    return np.zeros((n_quantities, NBINS + 1), dtype=np.int64)


@njit(cache=True, inline="always")
def staging(acc):
    """A float staging buffer for ``acc``: shape (n_quantities, NBINS + 2), zeroed.

    Every kernel that sums into an accumulator uses the same three calls, so none can forget
    to flush in time (which would silently lose exactness)::

        fbuf = exactsum.staging(acc)
        for i in ...:
            exactsum.add(fbuf, acc, q, value)      # flushes row q by itself when due
        exactsum.flush(fbuf, acc)                  # the rest, once at the end

    Columns 0..NBINS-1 hold the exact float partial sums of the bins, column NBINS counts
    out-of-range values and column NBINS+1 counts the additions since the row's last flush.
    """
    return np.zeros((acc.shape[0], NBINS + 2))


@njit(cache=True, inline="always")
def cut(x):
    """x (|x| < RANGE) cut into its four bins' pieces (q0, q1, q2, q3), each a multiple of
    its bin's ulp (the module docstring's q_k); the part below 2**-78 is dropped."""
    q0 = (x + M0) - M0
    r = x - q0
    q1 = (r + M1) - M1
    r = r - q1
    q2 = (r + M2) - M2
    r = r - q2
    q3 = (r + M3) - M3
    return q0, q1, q2, q3


@njit(cache=True, inline="always")
def add(fbuf, acc, q, x):
    """Add x to quantity q: cut it into the bins of ``fbuf`` (see ``staging``); every
    FLUSH_EVERY additions the row is moved into the int64 accumulator ``acc``.

    Out-of-range values (|x| >= RANGE, NaN, Inf) are counted in column NBINS instead.
    """
    if not (abs(x) < RANGE):  # also catches NaN
        fbuf[q, 4] += 1.0
    else:
        q0, q1, q2, q3 = cut(x)
        fbuf[q, 0] += q0
        fbuf[q, 1] += q1
        fbuf[q, 2] += q2
        fbuf[q, 3] += q3
    fbuf[q, 5] += 1.0
    if fbuf[q, 5] == FLUSH_EVERY:
        flush_row(fbuf, acc, q)


@njit(cache=True)
def flush_row(fbuf, acc, q):
    """Move row q of the staging buffer into the int64 accumulator and carry."""
    _move_row(fbuf, q, acc, q)


@njit(cache=True)
def _move_row(partial, r, acc, q):
    """Move the partial sums of row r of ``partial`` (``staging``'s layout) into quantity q of
    the int64 accumulator, zero them, and carry."""
    acc[q, 0] += np.int64(partial[r, 0] / ULP0)
    acc[q, 1] += np.int64(partial[r, 1] / ULP1)
    acc[q, 2] += np.int64(partial[r, 2] / ULP2)
    acc[q, 3] += np.int64(partial[r, 3] / ULP3)
    acc[q, 4] += np.int64(partial[r, 4])
    for k in range(NBINS + 2):
        partial[r, k] = 0.0
    normalize_row(acc[q])


@njit(cache=True)
def flush(fbuf, acc):
    """Move every row of the staging buffer into the accumulator (call once at the end)."""
    for q in range(fbuf.shape[0]):
        flush_row(fbuf, acc, q)


@njit(cache=True, inline="always")
def normalize_row(a):
    """Carry so that bins 1..NBINS-1 of one accumulator row hold values in [0, 2**41); the
    value is unchanged."""
    for k in range(NBINS - 1, 0, -1):
        c = a[k] >> _CARRY
        a[k] -= c << _CARRY
        a[k - 1] += c


# The items of one block of ``columns``: a power of two (an item's slot is i & (BLOCK - 1)). Each
# column costs a few calls, so longer blocks are cheaper a value (L-BFGS's dots, 17 quantities:
# 128 -> 256 items 14.0 -> 13.0 ns a sphere in 2D), until the buffer leaves the L2 cache (17
# quantities x 256 items: 82 KiB). The rows are padded: at 512 items a row is 4 KiB long, and
# an item's values, one a row, fell into one cache set (dots 3 times as slow).
COLUMN_BLOCK = 256
_ROW_PAD = 8


@njit(cache=True, inline="always")
def columns(acc):
    """A staging buffer for adding, item after item (a kernel's spheres), one value to each of
    several quantities of ``acc``, summed down each quantity's column a block of COLUMN_BLOCK
    items at a time: cutting a column into its bins' pieces and adding them up is one loop over
    contiguous values, which the compiler turns into vector instructions (per-value ``add``
    calls are not). The same three calls as ``staging``::

        cols = exactsum.columns(acc)
        for i in range(n):                        # items numbered 0, 1, ... n - 1
            exactsum.put(cols, q, i, value)       # for each quantity q of item i
            if exactsum.block_ends(i):            # the block is full: sum it
                exactsum.add_block(cols, acc)
        exactsum.flush_columns(cols, acc, n)

    The block's sum is called from the kernel's loop: an inlined helper that took the buffer
    and called it would cost reference counts at every item (docs/benchmarks.md, "Exact sums by
    columns"). One float64 array, not a tuple, for the same reason: shape (n_q + 1,
    COLUMN_BLOCK + _ROW_PAD), n_q = acc.shape[0]: rows [0, n_q) the block's values by quantity,
    then one row whose column q holds how many of quantity q's bins its blocks have needed so
    far (``add_columns``). A quantity not put for some items counts zeros for them. The
    accumulator is the same, bit for bit, as per-value ``add`` calls give: every value is cut
    the same way, and its pieces are added as integers (``_cut_sum_below_bin1``), exactly, in
    whatever order."""
    n_q = acc.shape[0]
    if n_q > COLUMN_BLOCK + _ROW_PAD:  # (row n_q holds one value a quantity)
        raise ValueError("exactsum.columns: more quantities than a row holds")
    return np.zeros((n_q + 1, COLUMN_BLOCK + _ROW_PAD))


@njit(cache=True, inline="always")
def put(cols, q, i, x):
    """Item i's value x of quantity q (see ``columns``)."""
    cols[q, i & (COLUMN_BLOCK - 1)] = x


@njit(cache=True, inline="always")
def block_ends(i):
    """Whether item i is the last of its block: then ``add_block`` is due (see ``columns``)."""
    return (i & (COLUMN_BLOCK - 1)) == COLUMN_BLOCK - 1


@njit(cache=True)
def add_block(cols, acc):
    """Sum a full block (after its last item's ``put`` calls; see ``columns``)."""
    add_columns(cols, acc, COLUMN_BLOCK)


# A column whose values are all below a bound has zero pieces in the bins above it: q_k =
# (r + M_k) - M_k is 0 when |r| < ulp(M_k) / 2 (half that bound here, for a margin), and r then
# passes on unchanged (r - 0 = r, also for -0.0). Such a column is cut into its lower bins only,
# the same pieces. Most columns are small (dot products of steps and forces: bins 2-3 only;
# positions: bins 1-3).
_BELOW_BIN1 = ULP1 / 4.0
_BELOW_BIN0 = ULP0 / 4.0
# The pieces are added as integers, in units of their bins' ulps: y = r + M_k lies in M_k's
# binade (|r| < M_k / 3), where a float64's bit pattern counts ulps, so the piece
# q_k = y - M_k is bits(y) - bits(M_k) ulps. Integer sums are exact in any order (no float
# reassociation, which could also fold (r + M) - M into r), and vectorise.
_BITS_M0, _BITS_M1, _BITS_M2, _BITS_M3 = (int(v) for v in _M.view(np.int64))


@njit(cache=True, error_model="numpy")
def _cut_sum_below_bin1(column, count):
    """(sum of bin 2's pieces, sum of bin 3's, in ulps; the number of values not below
    _BELOW_BIN1, NaN included) over column[:count]; the sums hold only if that number is 0."""
    s2 = 0
    s3 = 0
    large = 0
    for t in range(count):
        x = column[t]
        large += 0 if abs(x) < _BELOW_BIN1 else 1
        y2 = x + M2
        y3 = (x - (y2 - M2)) + M3
        s2 += float_bits(y2) - _BITS_M2
        s3 += float_bits(y3) - _BITS_M3
    return s2, s3, large


@njit(cache=True, error_model="numpy")
def _cut_sum_below_bin0(column, count):
    """``_cut_sum_below_bin1`` for the bins 1-3 and the bound _BELOW_BIN0."""
    s1 = 0
    s2 = 0
    s3 = 0
    large = 0
    for t in range(count):
        x = column[t]
        large += 0 if abs(x) < _BELOW_BIN0 else 1
        y1 = x + M1
        r = x - (y1 - M1)
        y2 = r + M2
        y3 = (r - (y2 - M2)) + M3
        s1 += float_bits(y1) - _BITS_M1
        s2 += float_bits(y2) - _BITS_M2
        s3 += float_bits(y3) - _BITS_M3
    return s1, s2, s3, large


@njit(cache=True, error_model="numpy")
def _cut_sum(column, count):
    """The sums of the four bins' pieces over column[:count] (``cut``), in ulps, and the number
    of out-of-range values (|x| >= RANGE, NaN, Inf), whose pieces are zeros."""
    s0 = 0
    s1 = 0
    s2 = 0
    s3 = 0
    bad = 0
    for t in range(count):
        x = column[t]
        ok = abs(x) < RANGE  # also False for NaN
        bad += 0 if ok else 1
        x = x if ok else 0.0
        y0 = x + M0
        r = x - (y0 - M0)
        y1 = r + M1
        r = r - (y1 - M1)
        y2 = r + M2
        y3 = (r - (y2 - M2)) + M3
        s0 += float_bits(y0) - _BITS_M0
        s1 += float_bits(y1) - _BITS_M1
        s2 += float_bits(y2) - _BITS_M2
        s3 += float_bits(y3) - _BITS_M3
    return s0, s1, s2, s3, bad


@njit(cache=True)
def add_columns(cols, acc, count):
    """Add the first ``count`` items of the block into ``acc`` and clear them. Each quantity is
    cut into as few bins as its values need (the same pieces: the upper ones are zeros): first
    the bins its earlier blocks needed (row n_q of ``cols``), more if a value is too large."""
    n_q = acc.shape[0]
    for q in range(n_q):
        column = cols[q]
        bins = cols[n_q, q]  # 0: bins 2-3, 1: bins 1-3, 2: all
        if bins == 0.0:
            s2, s3, large = _cut_sum_below_bin1(column, count)
            if large == 0:
                acc[q, 2] += s2
                acc[q, 3] += s3
            else:
                bins = 1.0
        if bins == 1.0:
            s1, s2, s3, large = _cut_sum_below_bin0(column, count)
            if large == 0:
                acc[q, 1] += s1
                acc[q, 2] += s2
                acc[q, 3] += s3
            else:
                bins = 2.0
        if bins == 2.0:
            s0, s1, s2, s3, bad = _cut_sum(column, count)
            acc[q, 0] += s0
            acc[q, 1] += s1
            acc[q, 2] += s2
            acc[q, 3] += s3
            acc[q, NBINS] += bad
        cols[n_q, q] = bins
        normalize_row(acc[q])  # (the ulps of a block's bin add to less than 2**50)
        for t in range(count):
            column[t] = 0.0


@njit(cache=True)
def flush_columns(cols, acc, n_items):
    """Sum the last, partial block (``n_items`` items put in all; call once at the end)."""
    rest = n_items & (COLUMN_BLOCK - 1)
    if rest > 0:
        add_columns(cols, acc, rest)


@njit(cache=True)
def accumulate(values, acc, q):
    """Exact sum of a 1-D float64 array into quantity q of ``acc``."""
    fbuf = staging(acc)
    for i in range(values.shape[0]):
        add(fbuf, acc, q, values[i])
    flush(fbuf, acc)


@njit(cache=True)
def value(acc, q):
    """float64 value of quantity q of a (possibly reduced) accumulator; NaN if it overflowed."""
    if acc[q, NBINS] != 0:
        return np.nan
    a = acc[q].copy()
    normalize_row(a)
    return ((float(a[0]) * ULP0 + float(a[1]) * ULP1) + float(a[2]) * ULP2) + float(a[3]) * ULP3


@njit(cache=True)
def values_all(acc):
    """float64 values of every quantity of a (possibly reduced) accumulator, shape
    (n_quantities,): ``value(acc, q)`` for each q in one call (NaN where it overflowed)."""
    out = np.empty(acc.shape[0])
    for q in range(acc.shape[0]):
        out[q] = value(acc, q)
    return out


def exact_sum(values):
    """Order-independent sum of a float64 array (serial helper, used in tests and metrics)."""
    acc = new_accumulator(1)
    accumulate(np.ascontiguousarray(values, dtype=np.float64).ravel(), acc, 0)
    return value(acc, 0)
