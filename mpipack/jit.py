"""numba's ``njit`` and ``cfunc``, with an on-disk cache that several processes may fill at once.

Every module of the package with compiled code imports them from here. Importing this module
makes one change to numba's cache (``IndexDataCacheFile.save``), for the processes of one MPI
job that compile the same functions at the same moment into one cache folder.

numba names a cached function's data files by number: a process saving a new signature reads
the index, takes the first free number n, writes ``name.n.nbc`` and then the index. Two
processes that compile two different signatures of one function together (say a literal
argument 3 on one rank and 4 on another, or a new cache folder after a source change) can both
take n = 1: the index left by one then points at the machine code the other wrote, and a later
run loads one signature's code for another's arguments (numba issue 4807: a segfault, or a
wrong result). Here the file is named by a digest of the whole key (signature, target, bytecode
hash), so a key's file can only ever hold that key's code. A race can still drop an index
entry, which costs one recompilation later, never a wrong load.
"""

import hashlib

from llvmlite import ir
from numba import cfunc, njit  # noqa: F401  (the package's one import of them)
from numba.core import caching, types
from numba.extending import intrinsic

__all__ = ["njit", "cfunc", "data_name", "float_bits"]


@intrinsic
def float_bits(typingctx, x):
    """The bit pattern of a float64 as an int64 (``x.view(np.int64)`` of a scalar, which numba
    lacks): a reinterpretation, no instruction, and vectorisable in a loop."""
    if x != types.float64:
        return None

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.IntType(64))

    return types.int64(types.float64), codegen


def data_name(index_name, key):
    """The data file of one cache entry: ``<function base>.<16 hex digits of the key's digest>.nbc``.

    ``index_name`` is the function's ``<base>.nbi``; ``key`` is numba's (signature, target,
    bytecode hashes) tuple, whose ``repr`` names every numba type uniquely.
    """
    base = index_name[: -len(".nbi")]
    digest = hashlib.sha256(repr(key).encode()).hexdigest()[:16]
    return f"{base}.{digest}.nbc"


def _save(self, key, data):
    """Save one entry: its data under a name only this key can have, then the index.

    The data is written before the index, so a reader never finds an entry whose file is not
    there yet; both writes are numba's own (a temporary file, then an atomic rename).
    """
    name = data_name(self._index_name, key)
    self._save_data(name, data)
    overloads = self._load_index()
    overloads[key] = name
    self._save_index(overloads)


_numbered_save = caching.IndexDataCacheFile.save  # numba's own, kept for the test that it races
caching.IndexDataCacheFile.save = _save
