"""Scenes: TOML files or built-in names, overrides, defaults and validation. No numerics.

A scene is a nested table; every key has a default (``DEFAULTS``) and a check. ``load`` merges,
validates and returns a ``Scene``: frozen, typed dataclasses read once by the run (attribute
access, no string keys in the loop). ``Scene.as_dict()`` gives the nested table back (for
summary.json and output files) and ``from_dict`` rebuilds a Scene from it.

Errors are ``SceneError`` with a one-line message naming the key; the CLI turns them into
exit code 2 on every rank.
"""

import copy
import functools
import dataclasses
import math
import os
import re
import tomllib
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Optional

METHODS = ("daha", "aha", "nap", "nav")
FORMS = ("S", "NS")
INIT_KINDS = ("gaussian", "ball", "lattice", "file")
STOP_RULES = ("certified", "eps", "jammed")
SCHEDULES = ("fixed", "fire-al")
# method parameters of the fixed schedule when a scene sets some but not all (the paper's
# section 4.3 values; gamma, if left out while alpha or beta is given, is sqrt(alpha beta):
# (2.10) exactly)
FIXED_FALLBACK = {"alpha": 7.8e-3, "beta": 2.8e3, "c": 2.0}
PAPER_GAMMA = 1.6e-2  # with the fallback alpha and beta
# stop.max_iter "auto": MAX_ITER_BASE up to N = MAX_ITER_N[b], then x (N / MAX_ITER_N[b])^p with
# p = MAX_ITER_GROWTH[b]. The bound is a safeguard, not a criterion: about twice the slowest
# certified run seen at the largest sizes measured. In 3D p = 1/3, the growth of the
# iterations per unit of the trap's time at a step bounded by the stiffest contact (3D N = 1e5
# certified in 16950 iterations under 232000). In 2D the polycrystal's grains slide for longer
# the larger the packing, and the slowest certified runs grew faster than N^(1/2): 7150
# iterations at N = 8000, 100500 at 32000, 556950 at 1e5 (seed 1, 2 ranks), which N^(1/2)'s
# 354000 cut short (docs/research/convergence.md, sections 3i, 3r and 3t): p = 1 there (400000 at
# 32000, 1250000 at 1e5). A 1D chain settles diffusively, about N^2 / 9 iterations (seeds 0
# and 1: 26900 and 39600 at N = 500, 77900 and 81950 at 1000, and seed 1 452500 at 2000,
# which the old bound of 100000 cut short): p = 2 from N = 633 (998000 at N = 2000).
MAX_ITER_BASE = 100000
MAX_ITER_N = {1: 633, 2: 8000, 3: 8000}
MAX_ITER_GROWTH = {1: 2.0, 2: 1.0, 3: 1.0 / 3.0}
MAX_ITER_LIMIT = 10 ** 12  # the largest stop.max_iter a scene may give


def auto_max_iter(n, dim):
    """The default iteration bound of a scene of n spheres in dim dimensions (see above), at
    most MAX_ITER_LIMIT (so that an absurd n is refused for its own sake, not for a bound the
    user never gave)."""
    grow = max(1.0, n / MAX_ITER_N[dim]) ** MAX_ITER_GROWTH[dim]
    return min(int(round(MAX_ITER_BASE * grow, -3)), MAX_ITER_LIMIT)

DEFAULTS = {
    "name": "scene",
    "dim": 2,
    "n": 2000,
    "seed": 1,
    "particles": {"diameter": 1.0, "diameter_max": None, "distribution": "uniform", "spread": None,
                  "sizes": None, "fractions": None, "file": None, "sha256": None},
    "init": {"kind": "gaussian", "sigma": "auto", "fraction": 0.5, "spacing": 1.0, "jitter": 0.0,
             "file": None, "iteration": None, "sha256": None},
    "method": {"name": "daha", "form": "S", "alpha": None, "beta": None, "gamma": None, "c": None,
               "schedule": None, "l_inner": 10, "eps_inner": 1e-9, "tau": 0.1},
    "stop": {"rule": None, "eps": 1e-5, "max_iter": "auto", "max_seconds": 0.0, "overlap": 1e-3,
             "kkt": 1e-2, "w_rtol": 1e-4, "w_window": 0.1, "check_every": 50, "watchdog": True,
             "jammed_rtol": 1e-3},
    "neighbor": {"skin": "auto", "adaptive_skin": True, "rebalance": 1.2, "max_pair_gib": None},
    "output": {"progress_every": 0.5, "dir": None, "metrics_every": 0, "w_optimum": None,
               "snapshots": True, "snapshot_every": 0, "checkpoint_every": 0},
    "container": {"kind": "none", "lo": None, "hi": None, "centre": None, "radius": None,
                  "height": None},
    "potential": {"kind": "centre", "point": None, "g": None},
}


class SceneError(ValueError):
    """Bad scene input: the message is one line and names the key."""


def builtin_names():
    return sorted(p.stem for p in resources.files("mpipack.scenes").iterdir() if p.name.endswith(".toml"))


# a scene file is a few hundred bytes: anything much larger is not one
MAX_SCENE_BYTES = 1024 * 1024
# the Verlet skin, in largest diameters: the rows hold every pair within d + skin, and their
# cost grows like (1 + skin)^b (neighbor.skin = 1e6 was accepted and 20x slower)
MAX_SKIN = 2.0
# neighbor.skin "auto": SKIN_AUTO, and SKIN_AUTO_FIRE_AL_2D / _3D as the adaptive skin's ceiling
# of a 2D / 3D fire-al run, whose pass skips the shell's entries cheaply (its rule's constant is
# larger: ``FireAL.skin_cost``): 2D N = 2000 and 2e4 jammed runs 5 - 12% sooner on 1 and 2
# ranks, a certified N = 2000 run 8% (docs/benchmarks.md, "A 2D jammed finish sooner than the
# quench"); 3D certified runs 3 - 8% sooner (session 47, "A wider adaptive skin in 3D"); a
# fixed DAHA's pass, which reads every entry, 11% slower with it
SKIN_AUTO, SKIN_AUTO_FIRE_AL_2D, SKIN_AUTO_FIRE_AL_3D = 0.3, 0.8, 0.6


def _read(source):
    """Parse a scene from a path or a built-in name."""
    if not source.strip():
        raise SceneError("empty scene name: give a TOML file or a built-in name (mpipack scenes)")
    path = Path(source)
    if path.suffix == ".toml" or path.exists():
        if not path.exists():
            raise SceneError(f"scene file not found: {source}")
        if path.is_dir():
            raise SceneError(f"scene {source} is a folder, not a TOML file")
        if not path.is_file():  # a device, a pipe: read without end
            raise SceneError(f"scene {source} is not a regular file")
        try:
            size = path.stat().st_size
        except OSError as e:
            raise SceneError(f"scene {source}: cannot read it: {e.strerror}") from None
        if size > MAX_SCENE_BYTES:
            raise SceneError(f"scene {source} has {size} bytes, more than a scene "
                             f"(at most {MAX_SCENE_BYTES // 1024} KiB)")
        try:
            text = path.read_text(encoding="utf-8")
        except UnicodeDecodeError:
            raise SceneError(f"scene {source} is not a text file (not UTF-8)") from None
        except OSError as e:
            raise SceneError(f"scene {source}: cannot read it: {e.strerror}") from None
        default_name = path.stem
    else:
        names = builtin_names()
        if source not in names:
            raise SceneError(f"unknown scene {source!r}: not a file, and not a built-in ({', '.join(names)})")
        text = resources.files("mpipack.scenes").joinpath(source + ".toml").read_text()
        default_name = source
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise SceneError(f"scene {source}: invalid TOML: {e}") from None
    if not data:
        raise SceneError(f"scene {source} sets no key (an empty file?); give at least one key, "
                         f"or run the default scene by name: mpipack run default")
    data.setdefault("name", default_name)
    return data


def _parse_value(text):
    """An override's value: TOML syntax (numbers, booleans, quoted strings), else a bare string."""
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def _merge(base, over, prefix=""):
    for key, val in over.items():
        dotted = prefix + key
        if key not in base:
            raise SceneError(f"unknown key '{dotted}'")
        if isinstance(base[key], dict):
            if not isinstance(val, dict):
                raise SceneError(f"key '{dotted}' is a table, got {val!r}")
            _merge(base[key], val, dotted + ".")
        else:
            if isinstance(val, dict):
                raise SceneError(f"key '{dotted}' is not a table")
            base[key] = val


DISTRIBUTIONS = ("uniform", "mono", "normal", "lognormal", "discrete", "file")
TRUNCATION = 3.0  # normal and lognormal diameters: within 3 standard deviations of the (log-)normal


@dataclass(frozen=True)
class Particles:
    """The diameters (``particles.distribution``; every draw a function of (seed, gid)):

    uniform    (default) uniform in [diameter, diameter_max]; all ``diameter`` without a max
    mono       all ``diameter``
    normal     mean ``diameter``, standard deviation ``spread`` x diameter, truncated to
               3 standard deviations (spread < 1/3, so that every diameter is positive)
    lognormal  mean ``diameter`` and standard deviation ``spread`` x diameter of the untruncated
               law: ln d ~ N(mu, s^2), s^2 = ln(1 + spread^2), mu = ln(diameter) - s^2 / 2,
               truncated to mu +- 3 s
    discrete   ``sizes`` in the proportions ``fractions``, in exact counts: the gids
               [N F_{k-1}, N F_k) (rounded, F the cumulative fractions) have size k
    file       the diameters of ``file`` (text, one a line, or a 1-D .npy; ``io.start``): with
               exactly N rows gid k has row k, else row draw(seed, gid) mod rows; or, under
               init.kind = "file" (``file`` None), the start file's own. ``sha256`` is the
               digest of the numbers read (``io.start``), recorded by ``load``; the law's
               figures (range, mean, mean radius powers) are the rows'
    """
    diameter: float
    diameter_max: Optional[float]
    distribution: str = "uniform"
    spread: Optional[float] = None
    sizes: Optional[list] = None
    fractions: Optional[list] = None
    file: Optional[str] = None
    sha256: Optional[str] = None

    @property
    def d_max(self):
        """Largest diameter of the scene."""
        return diameter_stats(self)[1]

    @property
    def d_mean(self):
        """The length unit of the schedule's law: the mean of the smallest and largest diameter
        for uniform and mono (as it always was), the distribution's mean for the others."""
        return diameter_stats(self)[2]

    def mean_radius_power(self, b):
        """The mean of (d/2)^b over the distribution (the measure of a mean sphere, over
        that of the unit ball)."""
        if self.distribution == "file":
            return file_law(self.sha256)[3][b - 1]
        return _radius_powers(self.distribution, self.diameter, self.diameter_max, self.spread,
                              tuple(self.sizes or ()), tuple(self.fractions or ()))[b - 1]


def diameter_stats(p):
    """(d_min, d_max, d_mean) of a ``Particles``."""
    if p.distribution == "file":
        return file_law(p.sha256)[:3]
    return _diameter_stats(p.distribution, p.diameter, p.diameter_max, p.spread,
                           tuple(p.sizes or ()), tuple(p.fractions or ()))


# the figures of the diameters files this process has read: sha256 -> (d_min, d_max, d_mean,
# (mean (d/2)^1, ^2, ^3)); every Scene is validated (``validate`` reads its file) before use
_FILE_LAWS = {}


def file_law(sha256):
    """(d_min, d_max, d_mean, radius powers) of the diameters file of this digest."""
    try:
        return _FILE_LAWS[sha256]
    except KeyError:
        raise SceneError(f"particles.distribution = \"file\": no file of sha256 {sha256} was read "
                         f"(a scene must come from config.load or from_dict)") from None


def _laws(kind, d, d_max, spread, sizes, fractions):
    """(diameters, weights) that describe the law: exact for mono and discrete; for uniform
    None (closed forms); for normal and lognormal a quadrature of the truncated law, the same
    bits in every process: scalar math.exp, no BLAS (whose dot product splits a sum over as
    many threads as it chooses), sums by math.fsum."""
    if kind == "discrete":
        return list(sizes), list(fractions)
    if kind in ("uniform", "mono"):
        return None
    import numpy as np
    z = np.linspace(-TRUNCATION, TRUNCATION, 20001)
    return ([float(v) for v in truncated_diameters(kind, d, spread, z)],
            [math.exp(-0.5 * float(v) * float(v)) for v in z])


def _weighted_mean(values, weights):
    return math.fsum(w * v for w, v in zip(weights, values)) / math.fsum(weights)


@functools.lru_cache(maxsize=64)
def _diameter_stats(kind, d, d_max, spread, sizes, fractions):
    if kind in ("uniform", "mono"):
        hi = d_max if (kind == "uniform" and d_max is not None) else d
        return d, hi, 0.5 * (d + hi)
    diam, weight = _laws(kind, d, d_max, spread, sizes, fractions)
    return min(diam), max(diam), _weighted_mean(diam, weight)


@functools.lru_cache(maxsize=64)
def _radius_powers(kind, d, d_max, spread, sizes, fractions):
    """(mean (d/2)^1, ^2, ^3) of the law."""
    if kind in ("uniform", "mono"):
        lo, hi, _ = _diameter_stats(kind, d, d_max, spread, sizes, fractions)
        if hi > lo:
            return tuple(((hi / 2) ** (b + 1) - (lo / 2) ** (b + 1)) / ((b + 1) * (hi - lo) / 2) for b in (1, 2, 3))
        return tuple((lo / 2) ** b for b in (1, 2, 3))
    diam, weight = _laws(kind, d, d_max, spread, sizes, fractions)
    return tuple(_weighted_mean([(v / 2) ** b for v in diam], weight) for b in (1, 2, 3))


def truncated_diameters(kind, d, spread, z):
    """The diameters of standard normal values z (|z| <= TRUNCATION) for the normal or lognormal
    law of mean d and relative spread ``spread`` (numpy arrays in, out)."""
    import numpy as np
    if kind == "normal":
        return d * (1.0 + spread * z)
    s2 = math.log1p(spread * spread)
    mu, s = math.log(d) - 0.5 * s2, math.sqrt(s2)
    # math.exp element by element: numpy's exp takes a SIMD path for some elements and a scalar
    # one for the rest, as the array's length and alignment fall, and the two can differ in the
    # last bit; a diameter must not depend on how many spheres a rank draws
    return np.fromiter((math.exp(mu + s * float(v)) for v in z), dtype=np.float64, count=len(z))


@dataclass(frozen=True)
class Init:
    kind: str
    sigma: object  # a length, or "auto": the paper's N = 2000 peak density at any N
    fraction: float
    spacing: float
    jitter: float
    file: Optional[str] = None  # init.kind = "file": the start (absolute path; io.start's formats)
    iteration: Optional[int] = None  # a snapshots file's snapshot (None: the last)
    sha256: Optional[str] = None  # the digest of the numbers read (io.start), recorded by load


@dataclass(frozen=True)
class Method:
    name: str
    form: str
    alpha: Optional[float]  # None under the fire-al schedule (it sets them per iteration)
    beta: Optional[float]
    gamma: Optional[float]
    c: Optional[float]
    schedule: str
    l_inner: int
    eps_inner: float
    tau: float

    @property
    def nested(self):
        return self.name in ("nap", "nav")


@dataclass(frozen=True)
class Stop:
    rule: str
    eps: float
    max_iter: int
    max_seconds: float
    overlap: float
    kkt: float
    w_rtol: float
    w_window: float
    check_every: int
    watchdog: bool
    jammed_rtol: float = 1e-3  # stop.rule = "jammed": W settled to this (``stop.rule``)


@dataclass(frozen=True)
class Neighbor:
    skin: float
    rebalance: float
    max_pair_gib: Optional[float]
    adaptive_skin: bool = True  # each build's skin from the last period's speed, at most skin


@dataclass(frozen=True)
class Output:
    progress_every: float
    dir: Optional[str]
    metrics_every: int
    w_optimum: Optional[float]
    snapshots: bool
    snapshot_every: int
    checkpoint_every: int


CONTAINERS = ("none", "box", "cylinder", "sphere")
# the densest packing fraction of equal spheres in b dimensions (1D a chain, 2D hexagonal,
# 3D face-centred cubic): no container can hold more of the spheres' measure than this
DENSEST = {1: 1.0, 2: math.pi / math.sqrt(12.0), 3: math.pi / math.sqrt(18.0)}


@dataclass(frozen=True)
class Container:
    """Walls that hold every sphere inside (``container.kind``), each a constraint per sphere
    with its own multiplier (``kernels.walls``):

    none      no wall (default: the paper's free cluster)
    box       ``lo`` <= X - d/2, X + d/2 <= ``hi`` along every axis (lists of b numbers)
    cylinder  3D: |X_xy - centre_xy| <= ``radius`` - d/2, a floor at centre_z and, with
              ``height``, a lid at centre_z + height
    sphere    |X - centre| <= ``radius`` - d/2 (a disc in 2D, an interval in 1D)
    """
    kind: str = "none"
    lo: Optional[list] = None
    hi: Optional[list] = None
    centre: Optional[list] = None
    radius: Optional[float] = None
    height: Optional[float] = None

    @property
    def active(self):
        return self.kind != "none"

    def volume(self, dim):
        """The container's measure (length^b); inf for an open cylinder."""
        if self.kind == "box":
            return math.prod(h - l for l, h in zip(self.lo, self.hi))
        if self.kind == "cylinder":
            return math.pi * self.radius ** 2 * self.height if self.height is not None else math.inf
        if self.kind == "sphere":
            return {1: 2.0 * self.radius, 2: math.pi * self.radius ** 2,
                    3: 4.0 / 3.0 * math.pi * self.radius ** 3}[dim]
        return math.inf

    def bottom(self, dim):
        """The lowest height (last coordinate) inside: a box's lo, a cylinder's floor, the
        bottom of a sphere."""
        if self.kind == "box":
            return self.lo[dim - 1]
        if self.kind == "cylinder":
            return self.centre[2]
        return self.centre[dim - 1] - self.radius

    def section(self, dim):
        """The measure of a horizontal cross-section (the floor's: a box's, a cylinder's
        disc; a sphere's at its equator), length^(b-1)."""
        if self.kind == "box":
            return math.prod(h - l for l, h in zip(self.lo[:dim - 1], self.hi[:dim - 1]))
        if self.kind == "cylinder":
            return math.pi * self.radius ** 2
        return {1: 1.0, 2: 2.0 * self.radius, 3: math.pi * self.radius ** 2}[dim]

    def middle(self, dim):
        """A point well inside: the box's centre, the cylinder's axis at its middle (an open one:
        a radius above the floor), the sphere's centre."""
        if self.kind == "box":
            return [0.5 * (l + h) for l, h in zip(self.lo, self.hi)]
        if self.kind == "cylinder":
            c = list(self.centre)
            c[2] += 0.5 * self.height if self.height is not None else self.radius
            return c
        return list(self.centre)


POTENTIALS = ("centre", "point", "gravity")


@dataclass(frozen=True)
class Potential:
    """What W pulls towards (``potential.kind``):

    centre   the paper's W = 1/(2N) sum_{i<j} |X_i - X_j|^2 = 1/2 sum_i |X_i - Xbar|^2: the
             centre of mass (default)
    point    W = 1/2 sum_i |X_i - P|^2, P = ``point`` (a list of b numbers): a fixed point
    gravity  W = g sum_i m_i (h_i - h_0), down along the last axis (y in 2D, z in 3D), h the
             last coordinate, h_0 the container's bottom, m_i = (d_i / d_mean)^b (a sphere of
             the mean diameter weighs 1); ``g`` (default 1) in units of d_mean and that mass.
             Needs a container (its floor holds the spheres)
    """
    kind: str = "centre"
    point: Optional[list] = None
    g: Optional[float] = None


_SECTIONS = {"particles": Particles, "init": Init, "method": Method, "stop": Stop,
             "neighbor": Neighbor, "output": Output, "container": Container, "potential": Potential}


@dataclass(frozen=True)
class Scene:
    """A validated scene. Sections are frozen dataclasses; ``replace`` makes a changed copy."""
    name: str
    dim: int
    n: int
    seed: int
    particles: Particles
    init: Init
    method: Method
    stop: Stop
    neighbor: Neighbor
    output: Output
    container: Container = Container()
    potential: Potential = Potential()

    def as_dict(self):
        return dataclasses.asdict(self)

    def replace(self, **sections):
        """A copy with top-level keys or whole sections changed; a section may be given as a
        dict of its changed keys, e.g. ``scene.replace(stop={"eps": 0.0})``."""
        changes = {}
        for key, val in sections.items():
            if isinstance(val, dict):
                val = dataclasses.replace(getattr(self, key), **val)
            changes[key] = val
        return dataclasses.replace(self, **changes)


def from_dict(data):
    """A Scene from a fully populated nested table (``Scene.as_dict`` output), validated."""
    scene = copy.deepcopy(DEFAULTS)
    _merge(scene, data)
    validate(scene, n_given="n" in data)
    return _freeze(scene)


def _freeze(table):
    kw = {k: table[k] for k in ("name", "dim", "n", "seed")}
    for sec, cls in _SECTIONS.items():
        kw[sec] = cls(**table[sec])
    return Scene(**kw)


def load(source=None, overrides=(), seed=None, base=None, settings=None):
    """Scene from a file or built-in name (default: the built-in 'default'), with
    ``overrides`` as 'dotted.key=value' strings, ``settings`` as {dotted key: value} and an
    optional seed, validated and frozen. With ``base`` (a scene table, e.g. a checkpoint's)
    and no source, the overrides apply to it."""
    scene = copy.deepcopy(DEFAULTS)
    # n comes from a start file unless given: by a base table, the user's scene file or a
    # --set / setting (a built-in scene's n is its default)
    n_given = False
    if base is not None and source is None:
        _merge(scene, base)
        n_given = "n" in base
    else:
        data = _read("default" if source is None else source)
        if source is not None and (Path(source).suffix == ".toml" or Path(source).exists()):  # _read's test
            n_given = "n" in data
            _files_beside(data, Path(source).parent)
        _merge(scene, data)
    for item in overrides:
        if "=" not in item:
            raise SceneError(f"--set expects key=value, got {item!r}")
        key, text = item.split("=", 1)
        parts = key.strip().split(".")
        n_given = n_given or key.strip() == "n"
        nested = _parse_value(text.strip())
        for p in reversed(parts):
            nested = {p: nested}
        _merge(scene, nested)
    for key, value in (settings or {}).items():
        nested = value
        for p in reversed(str(key).strip().split(".")):
            nested = {p: nested}
        _merge(scene, nested)
        n_given = n_given or str(key).strip() == "n"
    if seed is not None:
        scene["seed"] = seed
    validate(scene, n_given=n_given)
    return _freeze(scene)


def _files_beside(data, folder):
    """A scene file's relative init.file and particles.file are relative to its folder."""
    for section in ("init", "particles"):
        table = data.get(section)
        if isinstance(table, dict) and isinstance(table.get("file"), str) and table["file"] \
                and not Path(table["file"]).expanduser().is_absolute():
            table["file"] = str(folder / table["file"])


def _num(scene, dotted, kind=float, positive=True, allow_zero=False, optional=False):
    node = scene
    *path, last = dotted.split(".")
    for p in path:
        node = node[p]
    v = node[last]
    if v is None and optional:
        return None
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise SceneError(f"key '{dotted}' must be a number, got {v!r}")
    if kind is int:
        if isinstance(v, float):
            if not v.is_integer():
                raise SceneError(f"key '{dotted}' must be an integer, got {v!r}")
            v = int(v)
    else:
        v = float(v)
        if not math.isfinite(v):
            raise SceneError(f"key '{dotted}' must be finite, got {v!r}")
    if positive and (v < 0 or (v == 0 and not allow_zero)):
        raise SceneError(f"key '{dotted}' must be {'non-negative' if allow_zero else 'positive'}, got {v!r}")
    node[last] = v
    return v


def validate(scene, n_given=True):
    """Check types and ranges in place; raises SceneError naming the first bad key. With a start
    file (init.kind = "file") and ``n_given`` False, n is the file's row count."""
    if not isinstance(scene["name"], str) or not scene["name"]:
        raise SceneError("key 'name' must be a non-empty string")
    if not re.fullmatch(r"[A-Za-z0-9_][A-Za-z0-9_.+-]*", scene["name"]) or ".." in scene["name"]:
        raise SceneError(f"key 'name' must be a plain name (letters, digits, _ . + -; it names the "
                         f"output folder), got {scene['name']!r}")
    dim = _num(scene, "dim", int)
    if dim not in (1, 2, 3):
        raise SceneError(f"key 'dim' must be 1, 2 or 3, got {dim}")
    _num(scene, "n", int)
    seed = _num(scene, "seed", int, allow_zero=True)
    if seed >= 2 ** 63:
        raise SceneError(f"key 'seed' must be below 2**63, got {seed}")
    _check_files(scene, n_given)
    d = _num(scene, "particles.diameter")
    dmax = _num(scene, "particles.diameter_max", optional=True)
    if dmax is not None and dmax < d:
        raise SceneError(f"key 'particles.diameter_max' must be >= particles.diameter, got {dmax}")
    _check_distribution(scene)
    init = scene["init"]
    if init["kind"] not in INIT_KINDS:
        raise SceneError(f"key 'init.kind' must be one of {', '.join(INIT_KINDS)}, got {init['kind']!r}")
    if init["sigma"] != "auto":
        if isinstance(init["sigma"], str):
            raise SceneError(f"key 'init.sigma' must be a positive number or \"auto\", got {init['sigma']!r}")
        _num(scene, "init.sigma")
    if not 0 < _num(scene, "init.fraction") <= 64:
        raise SceneError(f"key 'init.fraction' (packing fraction of the ball start) must be in (0, 64], got {init['fraction']}")
    _num(scene, "init.spacing")
    _num(scene, "init.jitter", allow_zero=True)
    m = scene["method"]
    if m["name"] not in METHODS:
        raise SceneError(f"key 'method.name' must be one of {', '.join(METHODS)}, got {m['name']!r}")
    if m["form"] not in FORMS:
        raise SceneError(f"key 'method.form' must be S or NS, got {m['form']!r}")
    # a scene that leaves DAHA's parameters out gets the schedule that needs none; one that
    # sets any of them gets them, fixed, with the paper's section 4.3 values for the rest
    given = [k for k in ("alpha", "beta", "gamma", "c") if m[k] is not None]
    if m["schedule"] is None:
        m["schedule"] = "fire-al" if m["name"] == "daha" and not given else "fixed"
    if m["schedule"] not in SCHEDULES:
        raise SceneError(f"key 'method.schedule' must be one of {', '.join(SCHEDULES)}, got {m['schedule']!r}")
    if m["schedule"] == "fire-al":
        if m["name"] != "daha":
            raise SceneError(f"key 'method.schedule': \"fire-al\" schedules DAHA's own steps; method "
                             f"{m['name']!r} takes \"fixed\"")
        if given:
            raise SceneError(f"key 'method.{given[0]}': the fire-al schedule sets alpha, beta, gamma and c "
                             f"itself; leave them out, or set method.schedule = \"fixed\"")
    else:
        if m["alpha"] is None and m["beta"] is None and m["gamma"] is None:
            m["gamma"] = PAPER_GAMMA  # the paper's whole set, not sqrt of its alpha beta (4.67)
        for k, v in FIXED_FALLBACK.items():
            if m[k] is None:
                m[k] = v
        _fixed_parameters(scene)
    _num(scene, "method.l_inner", int)
    _num(scene, "method.eps_inner", allow_zero=True)
    _num(scene, "method.tau")
    if scene["stop"]["rule"] is None:  # the schedule's own: certified, or the paper's (4.3)
        scene["stop"]["rule"] = "certified" if m["schedule"] == "fire-al" else "eps"
    if scene["stop"]["rule"] not in STOP_RULES:
        raise SceneError(f"key 'stop.rule' must be one of {', '.join(STOP_RULES)}, got {scene['stop']['rule']!r}")
    _num(scene, "stop.eps", allow_zero=True)
    if scene["stop"]["max_iter"] == "auto":
        scene["stop"]["max_iter"] = auto_max_iter(scene["n"], scene["dim"])
    elif isinstance(scene["stop"]["max_iter"], str):
        raise SceneError(f"key 'stop.max_iter' must be a non-negative integer or \"auto\", "
                         f"got {scene['stop']['max_iter']!r}")
    _num(scene, "stop.max_iter", int, allow_zero=True)
    if scene["stop"]["max_iter"] > MAX_ITER_LIMIT:
        raise SceneError(f"key 'stop.max_iter' must be at most 1e12, got {scene['stop']['max_iter']}")
    _num(scene, "stop.max_seconds", allow_zero=True)
    _num(scene, "stop.overlap")
    _num(scene, "stop.kkt")
    _num(scene, "stop.w_rtol")
    if not 0 < _num(scene, "stop.w_window") <= 1:
        raise SceneError(f"key 'stop.w_window' is a fraction of the run, in (0, 1], got {scene['stop']['w_window']}")
    _num(scene, "stop.check_every", int)
    if not isinstance(scene["stop"]["watchdog"], bool):
        raise SceneError(f"key 'stop.watchdog' must be true or false, got {scene['stop']['watchdog']!r}")
    if not _num(scene, "stop.jammed_rtol") < 1:
        raise SceneError(f"key 'stop.jammed_rtol' is a relative change of W, in (0, 1), "
                         f"got {scene['stop']['jammed_rtol']!r}")
    if not isinstance(scene["neighbor"]["adaptive_skin"], bool):
        raise SceneError(f"key 'neighbor.adaptive_skin' must be true or false, "
                         f"got {scene['neighbor']['adaptive_skin']!r}")
    if scene["neighbor"]["skin"] == "auto":
        fire_al = m["schedule"] == "fire-al" and scene["neighbor"]["adaptive_skin"]
        scene["neighbor"]["skin"] = {2: SKIN_AUTO_FIRE_AL_2D, 3: SKIN_AUTO_FIRE_AL_3D}.get(
            scene["dim"], SKIN_AUTO) if fire_al else SKIN_AUTO
    elif isinstance(scene["neighbor"]["skin"], str):
        raise SceneError(f"key 'neighbor.skin' must be a number of largest diameters or \"auto\", "
                         f"got {scene['neighbor']['skin']!r}")
    if _num(scene, "neighbor.skin") > MAX_SKIN:
        raise SceneError(f"key 'neighbor.skin' is in largest diameters, at most {MAX_SKIN:g} "
                         f"(the pair rows grow like (1 + skin)^dim), got {scene['neighbor']['skin']!r}")
    if _num(scene, "stop.overlap") > 1:
        raise SceneError(f"key 'stop.overlap' is relative to the contact distance, at most 1, "
                         f"got {scene['stop']['overlap']!r}")
    _num(scene, "neighbor.max_pair_gib", optional=True)
    reb = _num(scene, "neighbor.rebalance")
    if reb < 1:
        raise SceneError(f"key 'neighbor.rebalance' must be >= 1 (max/mean particles per rank), got {reb}")
    _check_length_scales(scene)
    _num(scene, "output.progress_every", allow_zero=True)
    _num(scene, "output.metrics_every", int, allow_zero=True)
    _num(scene, "output.snapshot_every", int, allow_zero=True)
    _num(scene, "output.checkpoint_every", int, allow_zero=True)
    if not isinstance(scene["output"]["snapshots"], bool):
        raise SceneError(f"key 'output.snapshots' must be true or false, got {scene['output']['snapshots']!r}")
    _num(scene, "output.w_optimum", positive=False, optional=True)
    if scene["output"]["dir"] is not None and not isinstance(scene["output"]["dir"], str):
        raise SceneError("key 'output.dir' must be a string")
    _check_container(scene)
    _check_potential(scene)
    return scene


def _check_potential(scene):
    pot, dim = scene["potential"], scene["dim"]
    if pot["kind"] not in POTENTIALS:
        raise SceneError(f"key 'potential.kind' must be one of {', '.join(POTENTIALS)}, got {pot['kind']!r}")
    for key, kinds in (("point", ("point",)), ("g", ("gravity",))):
        if pot[key] is not None and pot["kind"] not in kinds:
            raise SceneError(f"key 'potential.{key}' does not apply to potential.kind = {pot['kind']!r}")
    if pot["kind"] == "centre":
        return
    if pot["kind"] == "gravity":
        if scene["container"]["kind"] == "none":
            raise SceneError("potential.kind = \"gravity\" needs a container to hold the spheres "
                             "(container.kind = \"box\", \"cylinder\" or \"sphere\")")
        if pot["g"] is None:
            pot["g"] = 1.0
        _num(scene, "potential.g")
        return
    v = pot["point"]
    if not isinstance(v, list) or len(v) != dim or not all(
            isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v):
        raise SceneError(f"potential.kind = \"point\" needs potential.point: a list of {dim} finite numbers, got {v!r}")
    pot["point"] = [float(x) for x in v]


def _vector(scene, key, dim):
    v = scene["container"][key]
    if not isinstance(v, list) or len(v) != dim or not all(
            isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v):
        raise SceneError(f"key 'container.{key}' must be a list of {dim} finite numbers (one per axis), got {v!r}")
    scene["container"][key] = [float(x) for x in v]
    return scene["container"][key]


def _check_container(scene):
    c, dim, n = scene["container"], scene["dim"], scene["n"]
    kind = c["kind"]
    if kind not in CONTAINERS:
        raise SceneError(f"key 'container.kind' must be one of {', '.join(CONTAINERS)}, got {kind!r}")
    used = {"none": (), "box": ("lo", "hi"), "cylinder": ("centre", "radius", "height"),
            "sphere": ("centre", "radius")}[kind]
    for key in ("lo", "hi", "centre", "radius", "height"):
        if c[key] is not None and key not in used:
            raise SceneError(f"key 'container.{key}' does not apply to container.kind = {kind!r}")
        if c[key] is None and key in used and key != "height":
            raise SceneError(f"container.kind = {kind!r} needs container.{key}")
    if kind == "none":
        return
    law = Particles(**scene["particles"])
    d_max = law.d_max
    if kind == "box":
        lo, hi = _vector(scene, "lo", dim), _vector(scene, "hi", dim)
        for k in range(dim):
            if hi[k] - lo[k] < d_max:
                raise SceneError(f"keys 'container.lo' and 'container.hi': the box is {hi[k] - lo[k]:g} wide "
                                 f"along axis {k}, narrower than the largest diameter {d_max:g}")
    else:
        _vector(scene, "centre", dim)
        if kind == "cylinder" and dim != 3:
            raise SceneError(f"container.kind = \"cylinder\" is a 3D container (its axis along z); in {dim}D "
                             f"use \"box\" or \"sphere\"")
        radius = _num(scene, "container.radius")
        if 2.0 * radius < d_max:
            raise SceneError(f"key 'container.radius' = {radius:g} holds no sphere of the largest diameter {d_max:g}")
        if kind == "cylinder" and _num(scene, "container.height", optional=True) is not None \
                and c["height"] < d_max:
            raise SceneError(f"key 'container.height' = {c['height']:g} is lower than the largest diameter {d_max:g}")
    # the spheres' measure against what the container can hold at the densest packing
    spheres = n * _ball_measure(dim) * law.mean_radius_power(dim)
    room = DENSEST[dim] * Container(**c).volume(dim)
    if spheres > room:
        raise SceneError(f"the container is too small: {n} spheres fill {spheres:.4g} (length^{dim}), more than "
                         f"the {room:.4g} it holds at the densest packing ({DENSEST[dim]:.4f} of its "
                         f"{Container(**c).volume(dim):.4g}); enlarge it or use fewer spheres")


def _ball_measure(dim):
    return {1: 2.0, 2: math.pi, 3: 4.0 / 3.0 * math.pi}[dim]


def _fixed_parameters(scene):
    m = scene["method"]
    alpha = _num(scene, "method.alpha")
    beta = _num(scene, "method.beta")
    _num(scene, "method.c")
    if _num(scene, "method.gamma", allow_zero=True, optional=True) is None:
        m["gamma"] = math.sqrt(alpha * beta)


def _check_distribution(scene):
    p = scene["particles"]
    kind = p["distribution"]
    if kind not in DISTRIBUTIONS:
        raise SceneError(f"key 'particles.distribution' must be one of {', '.join(DISTRIBUTIONS)}, got {kind!r}")
    used = {"uniform": ("diameter_max",), "mono": (), "normal": ("spread",), "lognormal": ("spread",),
            "discrete": ("sizes", "fractions"), "file": ("file", "sha256")}[kind]
    for key in ("diameter_max", "spread", "sizes", "fractions", "file", "sha256"):
        if p[key] is not None and key not in used:
            raise SceneError(f"key 'particles.{key}' does not apply to particles.distribution = {kind!r}")
    if kind in ("normal", "lognormal"):
        if p["spread"] is None:
            raise SceneError(f"particles.distribution = {kind!r} needs particles.spread (standard deviation / mean)")
        spread = _num(scene, "particles.spread")
        if kind == "normal" and spread >= 1.0 / TRUNCATION:
            raise SceneError(f"key 'particles.spread' must be below 1/3 for a normal law truncated at 3 "
                             f"standard deviations (every diameter positive), got {spread}")
        if kind == "lognormal" and spread > 10:
            raise SceneError(f"key 'particles.spread' must be at most 10, got {spread}")
    if kind == "discrete":
        sizes, fractions = p["sizes"], p["fractions"]
        for key, v in (("sizes", sizes), ("fractions", fractions)):
            if not isinstance(v, list) or not v or not all(
                    isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) and x > 0 for x in v):
                raise SceneError(f"particles.distribution = \"discrete\" needs particles.{key}: a list of "
                                 f"positive numbers, got {v!r}")
        if len(sizes) != len(fractions):
            raise SceneError(f"keys 'particles.sizes' and 'particles.fractions' must have the same length, "
                             f"got {len(sizes)} and {len(fractions)}")
        p["sizes"], p["fractions"] = [float(x) for x in sizes], [float(x) for x in fractions]


# Lengths must stay where the exact sums resolve them: |X|^2 below exactsum.RANGE (~3.9e25,
# |X| < 6e12) with room for the run to expand, and well above its resolution (2^-78).
LENGTH_MIN, LENGTH_MAX = 1e-6, 1e9


def _check_length_scales(scene):
    p, init = scene["particles"], scene["init"]
    dim, n = scene["dim"], scene["n"]
    if p["distribution"] == "file":
        d_min, d_max = file_law(p["sha256"])[:2]
    else:
        d_min, d_max = _diameter_stats(p["distribution"], p["diameter"], p["diameter_max"], p["spread"],
                                       tuple(p["sizes"] or ()), tuple(p["fractions"] or ()))[:2]
    lengths = {"particles.diameter": d_min, "particles.diameter_max": d_max,
               # the packed cloud's extent
               "n and particles.diameter (the packing's size)": d_max * n ** (1.0 / dim)}
    if init["kind"] == "gaussian" and init["sigma"] != "auto":
        lengths["init.sigma"] = init["sigma"]
    if init["kind"] == "lattice":
        lengths["init.spacing"] = init["spacing"] * n ** (1.0 / dim)
    for key, v in lengths.items():
        if not LENGTH_MIN <= v <= LENGTH_MAX:
            raise SceneError(f"key '{key.split(' ')[0]}': length {v:.3g} is outside [{LENGTH_MIN:g}, "
                             f"{LENGTH_MAX:g}] ({key}); rescale the problem (results scale with d)")


def _check_files(scene, n_given):
    """A start file (init.kind = "file") or a diameters file (particles.distribution = "file"):
    read (``io.start``, one-line errors naming the file), n taken from the start file unless
    given, paths made absolute, the digest of the numbers recorded (a digest already in the
    scene, e.g. a checkpoint's, must match: the file has not changed) and the diameters' law
    registered (``file_law``)."""
    init, p = scene["init"], scene["particles"]
    if init["kind"] != "file":
        for key in ("file", "iteration", "sha256"):
            if init[key] is not None:
                raise SceneError(f"key 'init.{key}' applies to init.kind = \"file\" "
                                 f"(init.kind is {init['kind']!r})")
        if p["distribution"] == "file":
            _path(scene, "particles.file")
            info = _read_start("particles.file", p["file"], lambda s: s.read_diameters(p["file"]))
            _record(scene, "particles", info)
        return
    _path(scene, "init.file")
    if init["iteration"] is not None:
        if isinstance(init["iteration"], str):
            raise SceneError(f"key 'init.iteration' must be a non-negative integer, got {init['iteration']!r}")
        _num(scene, "init.iteration", int, allow_zero=True)
    # the diameters are the file's: the particles section keeps its defaults ("file" once resolved)
    given = [k for k in ("diameter_max", "spread", "sizes", "fractions", "file") if p[k] is not None]
    if p["distribution"] not in ("uniform", "file") or given:
        key = "particles.distribution" if p["distribution"] not in ("uniform", "file") else f"particles.{given[0]}"
        raise SceneError(f"key '{key}': init.kind = \"file\" takes the diameters from init.file; "
                         f"leave the particles section out")
    info = _read_start("init.file", init["file"],
                       lambda s: s.read_start(init["file"], scene["dim"], init["iteration"]))
    if n_given and scene["n"] != info.rows:
        raise SceneError(f"key 'n': the scene gives n = {scene['n']}, init.file {init['file']} has "
                         f"{info.rows} rows; leave n out (it is the file's) or make them agree")
    scene["n"] = info.rows
    if not info.extent <= LENGTH_MAX:
        raise SceneError(f"key 'init.file': {info.source}: a coordinate of {info.extent:.3g}, beyond "
                         f"{LENGTH_MAX:g}; rescale the problem (results scale with d)")
    _record(scene, "init", info)
    p["distribution"] = "file"
    _record(scene, "particles", info)


def _path(scene, dotted):
    section, key = dotted.split(".")
    v = scene[section][key]
    if not isinstance(v, str) or not v.strip():
        what = "init.kind = \"file\"" if section == "init" else "particles.distribution = \"file\""
        raise SceneError(f"{what} needs {dotted}: a file's path, got {v!r}")
    scene[section][key] = os.path.abspath(os.path.expanduser(v))


def _read_start(dotted, path, read):
    from mpipack.io import start
    try:
        return read(start)
    except start.StartError as e:
        raise SceneError(f"key '{dotted}': {e}") from None


def _record(scene, section, info):
    """The file's digest in scene[section]["sha256"] (checked against one already there) and its
    diameters' law registered."""
    table = scene[section]
    if table["sha256"] is not None and table["sha256"] != info.sha256:
        raise SceneError(f"key '{section}.sha256': {info.source} holds other numbers than the scene "
                         f"records (sha256 {info.sha256[:12]}..., recorded {str(table['sha256'])[:12]}...): "
                         f"the file changed")
    table["sha256"] = info.sha256
    _FILE_LAWS[info.sha256] = (info.d_min, info.d_max, info.d_mean, info.radius_powers)


# what a restart may change: how the run stops, what it writes, how it splits the work; never
# what it computes
RESTART_MAY_CHANGE = ("name", "stop", "output", "neighbor")


def physics_changes(old, new):
    """Dotted keys whose values differ between two scene tables, outside RESTART_MAY_CHANGE,
    as 'key (old -> new)' strings."""
    out = []
    for key in sorted(set(old) | set(new)):
        if key in RESTART_MAY_CHANGE:
            continue
        a, b = old.get(key), new.get(key)
        if isinstance(DEFAULTS.get(key), dict):  # a section the old scene did not have yet held defaults
            a, b = a if a is not None else {}, b if b is not None else {}
        if isinstance(a, dict) and isinstance(b, dict):
            # a key the old scene did not have yet held its default
            default = DEFAULTS.get(key, {}) if isinstance(DEFAULTS.get(key), dict) else {}
            out += [f"{key}.{k} ({a.get(k, default.get(k))!r} -> {b.get(k, default.get(k))!r})"
                    for k in sorted(set(a) | set(b)) if a.get(k, default.get(k)) != b.get(k, default.get(k))]
        elif a != b:
            out.append(f"{key} ({a!r} -> {b!r})")
    return out


def d_max(scene):
    """Largest diameter of the scene."""
    return scene.particles.d_max
