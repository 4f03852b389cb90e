"""mpipack: MPI-parallel sphere packing with the damped Arrow-Hurwicz algorithm.

The library API (``api``): ``run``, ``load_scene``, ``read_snapshot`` and their ``Result``,
``Snapshot``. Importing the package imports neither numpy, numba nor mpi4py.
"""

import hashlib
import os
from pathlib import Path

__version__ = "0.1.0"


def _numba_cache_dir():
    """Numba's on-disk cache keyed by a hash of this package's sources.

    numba invalidates a cached function when its own file changes, not when a function it
    inlines from another module does (kernels inline exactsum.add): a stale cache would then
    run old code. A cache folder per hash of every source file of the package, subpackages
    included, cannot be stale. Set before numba is imported; a NUMBA_CACHE_DIR chosen by the
    user is left alone.
    """
    here = Path(__file__).resolve().parent
    h = hashlib.sha256()
    for p in sorted(here.rglob("*.py")):
        h.update(p.relative_to(here).as_posix().encode())
        h.update(p.read_bytes())
    return str(here / "__pycache__" / f"numba-{h.hexdigest()[:16]}")


if "NUMBA_CACHE_DIR" not in os.environ:
    try:
        os.environ["NUMBA_CACHE_DIR"] = _numba_cache_dir()
    except OSError:
        pass


from mpipack.api import Result, Snapshot, load_scene, read_snapshot, run  # noqa: E402

__all__ = ["run", "load_scene", "read_snapshot", "Result", "Snapshot", "__version__"]
