"""The layers of docs/architecture.md, kept true: every import of every module of the package
(top-level and inside functions) against the table of what each layer may import."""

import ast
import re
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "mpipack"

# layer -> the mpipack modules it may import (prefixes); "mpipack.errors" and "mpipack.config"
# are shared by every layer above the kernels
SHARED = ("mpipack.errors", "mpipack.config", "mpipack.__version__", "mpipack.jit")
MAY_IMPORT = {
    "kernels": ("mpipack.kernels", "mpipack.parallel.exactsum", "mpipack.jit"),
    "parallel": ("mpipack.parallel", "mpipack.jit"),
    "io": ("mpipack.io", "mpipack.__version__"),
    "methods": ("mpipack.methods", "mpipack.kernels", "mpipack.parallel.reduction",
                "mpipack.parallel.neighbors", "mpipack.parallel.exactsum") + SHARED,
    "stop": ("mpipack.stop", "mpipack.kernels", "mpipack.parallel", "mpipack.methods.fire_al_schedule") + SHARED,
    "engine": ("mpipack.engine", "mpipack.methods", "mpipack.stop", "mpipack.kernels", "mpipack.parallel",
               "mpipack.io") + SHARED,
    "analysis": ("mpipack.analysis", "mpipack.engine.initial", "mpipack.engine.memory", "mpipack.kernels",
                 "mpipack.parallel", "mpipack.methods") + SHARED,
    "experiments": ("mpipack.experiments", "mpipack.engine", "mpipack.analysis", "mpipack.post", "mpipack.parallel",
                    "mpipack.methods", "mpipack.stop", "mpipack.io", "mpipack.kernels") + SHARED,
    "post": ("mpipack.post", "mpipack.io", "mpipack.parallel", "mpipack.kernels.metrics",
             "mpipack.kernels.walls") + SHARED,
    "cli": ("mpipack.cli", "mpipack.engine", "mpipack.analysis", "mpipack.experiments", "mpipack.io",
            "mpipack.parallel", "mpipack.stop.signals", "mpipack.post") + SHARED,
    "api": ("mpipack.engine.runner", "mpipack.io", "mpipack.parallel.comm", "mpipack.stop.signals") + SHARED,
    "config": ("mpipack.config", "mpipack.io.start"),  # a start file's rows and diameters at load
    "scenes": (),
    "errors": (),
    "jit": (),
}
# modules that may import mpi4py: the communicator, and parallel HDF5's file access
MPI_MODULES = {"mpipack.parallel.comm", "mpipack.io._h5"}


def module_name(path):
    rel = path.relative_to(PACKAGE.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def imports(path):
    """Every (module imported, line) of a file, relative imports resolved."""
    name = module_name(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out += [(a.name, node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")
                parts = parts[: len(parts) - node.level + 1]
                base = ".".join(parts + ([node.module] if node.module else []))
            for a in node.names:  # "from mpipack.x import y": y may be a module or a name
                out.append((f"{base}.{a.name}", node.lineno))
    return out


def layer(name):
    parts = name.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


MODULES = sorted(p for p in PACKAGE.rglob("*.py") if "__pycache__" not in p.parts)


def test_every_module_is_in_a_layer():
    layers = {layer(module_name(p)) for p in MODULES} - {"__init__"}
    assert layers <= set(MAY_IMPORT), layers - set(MAY_IMPORT)


@pytest.mark.parametrize("path", MODULES, ids=lambda p: module_name(p))
def test_imports_follow_the_layers(path):
    name = module_name(path)
    here = layer(name)
    bad = []
    for target, line in imports(path):
        if target.split(".")[0] == "mpi4py" and name not in MPI_MODULES:
            bad.append(f"line {line}: {target} (only {sorted(MPI_MODULES)} may import mpi4py)")
        if not target.startswith("mpipack.") or here == "__init__":
            continue
        if not any(target == p or target.startswith(p + ".") for p in MAY_IMPORT[here]):
            bad.append(f"line {line}: {target}")
    assert not bad, f"{name} ({here} layer) imports outside its layer: {bad}"


def test_nothing_imports_the_cli_or_the_experiments_from_below():
    """The CLI is a leaf: no module outside it imports it (the library API does not parse argv)."""
    for path in MODULES:
        name = module_name(path)
        for target, line in imports(path):
            if target.startswith("mpipack.cli") and not name.startswith("mpipack.cli"):
                pytest.fail(f"{name} line {line} imports the CLI ({target})")


def test_the_checker_sees_a_violation(tmp_path):
    """The check can fail: a kernel module that imports the communicator is caught."""
    bad = PACKAGE / "kernels" / "_probe_bad.py"
    bad.write_text("from mpipack.parallel import comm\nimport mpi4py\n")
    try:
        with pytest.raises(AssertionError, match="kernels layer"):
            test_imports_follow_the_layers(bad)
    finally:
        bad.unlink()


@pytest.mark.parametrize("path", MODULES, ids=lambda p: module_name(p))
def test_compiled_code_is_cached_through_mpipack_jit(path):
    """numba's njit and cfunc come from mpipack.jit, whose cache several ranks may fill at once
    (tests/test_jit_cache.py); a module that took them from numba itself would bypass it."""
    if module_name(path) == "mpipack.jit":
        return
    text = path.read_text()
    direct = [line for line, target in ((n, t) for t, n in imports(path))
              if target in ("numba.njit", "numba.jit", "numba.cfunc")]
    direct += [m.start() for m in re.finditer(r"\bnumba\.(njit|jit|cfunc)\(", text)]
    assert not direct, f"{module_name(path)} takes njit/cfunc from numba, not mpipack.jit"
