"""Scenes: built-ins, overrides, validation (in-process, no MPI)."""

import math

import pytest

from mpipack import config


def test_builtin_scenes():
    assert {"default", "paper-3d", "two-spheres"} <= set(config.builtin_names())
    d = config.load()
    assert d.name == "default" and d.dim == 2 and d.n == 2000
    # the main job: the schedule that needs no parameters, and the certified stop
    m = d.method
    assert (m.name, m.form, m.schedule, m.alpha, m.beta, m.gamma, m.c) == ("daha", "S", "fire-al", None, None, None, None)
    assert d.stop.rule == "certified" and d.init.sigma == "auto"
    p2 = config.load("paper-2d")
    m = p2.method
    assert (m.name, m.form, m.schedule, m.alpha, m.beta, m.gamma, m.c) == ("daha", "S", "fixed", 7.8e-3, 2.8e3, 1.6e-2, 2.0)
    assert p2.stop.eps == 1e-5 and p2.stop.rule == "eps"
    p3 = config.load("paper-3d")
    assert p3.dim == 3 and p3.stop.eps == 0.0 and p3.method.gamma == 5.6e-2
    two = config.load("two-spheres")
    assert two.dim == 1 and two.n == 2 and two.method.form == "NS"
    # no gamma given: (2.10) exactly, gamma = sqrt(alpha beta)
    assert two.method.gamma == pytest.approx(math.sqrt(0.3 * 3.0), rel=1e-15)
    # every key is populated, and the table form rebuilds the same scene
    table = d.as_dict()
    assert set(table) == set(config.DEFAULTS)
    for sec, keys in config.DEFAULTS.items():
        if isinstance(keys, dict):
            assert set(table[sec]) == set(keys), sec
    assert config.from_dict(table) == d


def test_scene_is_frozen():
    d = config.load()
    with pytest.raises(AttributeError):
        d.n = 5
    with pytest.raises(AttributeError):
        d.method.alpha = 1.0
    e = d.replace(n=10, stop={"eps": 0.0})
    assert (e.n, e.stop.eps, e.stop.max_iter) == (10, 0.0, d.stop.max_iter) and d.n == 2000


@pytest.mark.parametrize("sets,skin", [
    ([], config.SKIN_AUTO_FIRE_AL_2D),                               # 2D fire-al, adaptive
    (["dim=3"], config.SKIN_AUTO_FIRE_AL_3D),                        # 3D fire-al, adaptive
    (["dim=3", "neighbor.adaptive_skin=false"], config.SKIN_AUTO),
    (["dim=1"], config.SKIN_AUTO),
    (["neighbor.adaptive_skin=false"], config.SKIN_AUTO),            # a fixed skin stays 0.3
    (["method.alpha=0.01"], config.SKIN_AUTO),                       # the fixed DAHA
    (["method.name=nap"], config.SKIN_AUTO),
    (["neighbor.skin=0.45"], 0.45),                                  # a value is the value
    (['neighbor.skin="auto"', "dim=3"], config.SKIN_AUTO_FIRE_AL_3D),
])
def test_the_auto_skin_is_wider_only_for_fire_al(sets, skin):
    """neighbor.skin "auto" resolves to a number in the resolved scene: 0.8 for a 2D run of
    the fire-al schedule under the adaptive skin, 0.6 for a 3D one, 0.3 otherwise."""
    s = config.load("default", sets)
    assert s.neighbor.skin == skin and isinstance(s.neighbor.skin, float)
    assert (config.SKIN_AUTO, config.SKIN_AUTO_FIRE_AL_2D, config.SKIN_AUTO_FIRE_AL_3D) == (0.3, 0.8, 0.6)


def test_overrides_and_seed():
    s = config.load("default", ["n=50", "stop.eps=0", "dim=3", "method.form=NS",
                                "method.name=aha", "init.kind=lattice",
                                "particles.diameter_max=1.3", "neighbor.skin=0.5"], seed=9)
    assert s.n == 50 and isinstance(s.n, int)
    assert s.stop.eps == 0.0 and isinstance(s.stop.eps, float)
    assert s.dim == 3 and s.method.form == "NS" and s.method.name == "aha"
    assert s.init.kind == "lattice" and s.particles.diameter_max == 1.3
    assert s.seed == 9 and s.neighbor.skin == 0.5
    assert config.d_max(s) == 1.3
    assert config.load("default", ["n=50.0"]).n == 50
    # a later override wins
    assert config.load("default", ["n=50", "n=60"]).n == 60


def test_scene_file(tmp_path):
    f = tmp_path / "mine.toml"
    f.write_text('dim = 3\nn = 10\n[method]\nform = "NS"\nalpha = 0.1\nbeta = 0.4\n')
    s = config.load(str(f))
    assert s.name == "mine" and s.dim == 3 and s.n == 10
    assert s.method.gamma == pytest.approx(0.2, rel=1e-15)
    # a fixed scheme: (4.3); "auto" bound of N = 10
    assert s.as_dict()["stop"] == {**config.DEFAULTS["stop"], "rule": "eps", "max_iter": 100000}


BAD = [
    ("bogus=1", "bogus"),
    ("method.alhpa=1", "method.alhpa"),
    ("stop.eps.x=1", "stop.eps"),
    ("method=1", "method"),
    ("n=0", "'n'"),
    ("n=-3", "'n'"),
    ("n=2.5", "'n'"),
    ("n=abc", "'n'"),
    ("n=true", "'n'"),
    ("dim=4", "'dim'"),
    ("dim=0", "'dim'"),
    ("method.alpha=-1", "method.alpha"),
    ("method.beta=0", "method.beta"),
    ("method.beta=nan", "method.beta"),
    ("method.alpha=inf", "method.alpha"),
    ("method.c=0", "method.c"),
    ("method.gamma=-1", "method.gamma"),
    ("method.name=sqp", "method.name"),
    ("method.form=X", "method.form"),
    ("particles.diameter=0", "particles.diameter"),
    ("particles.diameter_max=0.5", "particles.diameter_max"),
    ("init.kind=grid", "init.kind"),
    ("init.sigma=0", "init.sigma"),
    ("init.sigma=wide", "init.sigma"),
    ("init.fraction=0", "init.fraction"),
    ("stop.rule=fast", "stop.rule"),
    ("stop.w_window=2", "stop.w_window"),
    ("stop.kkt=0", "stop.kkt"),
    ("stop.check_every=0", "stop.check_every"),
    ("stop.eps=-1", "stop.eps"),
    ("stop.max_iter=-1", "stop.max_iter"),
    ('stop.max_iter="many"', "stop.max_iter"),
    ("neighbor.skin=0", "neighbor.skin"),
    ("neighbor.skin=1e6", "neighbor.skin"),
    ('neighbor.skin="wide"', "neighbor.skin"),
    ("stop.overlap=2", "stop.overlap"),
    ("neighbor.rebalance=0.9", "neighbor.rebalance"),
    ("seed=-1", "seed"),
    ("name=", "name"),
    ("output.dir=1", "output.dir"),
    ("no-equals-sign", "no-equals-sign"),
]


@pytest.mark.parametrize("override,key", BAD, ids=[b[0] for b in BAD])
def test_bad_override_names_the_key(override, key):
    with pytest.raises(config.SceneError) as e:
        config.load("default", [override])
    msg = str(e.value)
    assert key in msg, msg
    assert "\n" not in msg


def test_bad_scene_source(tmp_path):
    with pytest.raises(config.SceneError, match="no-such"):
        config.load("no-such-scene")
    with pytest.raises(config.SceneError, match="not found"):
        config.load(str(tmp_path / "missing.toml"))
    f = tmp_path / "broken.toml"
    f.write_text("dim = [\n")
    with pytest.raises(config.SceneError, match="invalid TOML"):
        config.load(str(f))
    g = tmp_path / "typo.toml"
    g.write_text("[particles]\ndiameter = 1.0\nradius = 0.5\n")
    with pytest.raises(config.SceneError, match="particles.radius"):
        config.load(str(g))
    # damaged or wrong input, refused in one line before anything is read without bound
    with pytest.raises(config.SceneError, match="not a regular file"):
        config.load("/dev/zero")
    e = tmp_path / "empty.toml"
    e.write_text("# nothing yet\n")
    with pytest.raises(config.SceneError, match="sets no key"):
        config.load(str(e))
    big = tmp_path / "big.toml"
    big.write_text("# " + "x" * (config.MAX_SCENE_BYTES + 10) + "\n")
    with pytest.raises(config.SceneError, match="more than a scene"):
        config.load(str(big))


def test_iteration_bound_grows_with_n(tmp_path):
    """stop.max_iter "auto" (the default scene's and any scene that leaves the key out): 100000
    up to N = 8000, then x (N / 8000)^p, p = 1/3 in 3D, 1 in 2D (the slowest certified 2D runs:
    100500 iterations at N = 32000, 556950 at 1e5); a number given is kept, paper scenes keep
    theirs."""
    bound = {(n, dim): config.load("default", [f"n={n}", f"dim={dim}"]).stop.max_iter
             for n, dim in [(2, 2), (8000, 2), (32000, 2), (100000, 2), (100000, 3), (1000000, 2)]}
    assert bound == {(2, 2): 100000, (8000, 2): 100000, (32000, 2): 400000, (100000, 2): 1250000,
                     (100000, 3): 232000, (1000000, 2): 12500000}
    assert bound[(100000, 2)] > 2 * 556950  # the one certified 2D N = 1e5 run, twice over
    # 1D: like N^2 (a chain settles diffusively): 1D N = 2000 seed 1 certifies at 452500
    assert config.load("default", ["n=2000", "dim=1"]).stop.max_iter > 2 * 452500
    assert config.load("default", ["n=500", "dim=1"]).stop.max_iter == 100000
    # never above what a scene may give (an absurd n is refused for its memory, not its bound)
    assert config.auto_max_iter(10 ** 12, 2) == config.MAX_ITER_LIMIT
    assert config.load("default", ["n=100000", "stop.max_iter=5"]).stop.max_iter == 5
    assert config.load("default", ["stop.max_iter=\"auto\""]).stop.max_iter == 100000
    assert config.load("paper-3d", ["n=100000"]).stop.max_iter == 10000
    f = tmp_path / "s.toml"
    f.write_text("n = 256000\ndim = 3\n")
    assert config.load(str(f), []).stop.max_iter == 317000


def test_starts_that_scale():
    """init.sigma = "auto" keeps the peak density of the paper's N = 2000 start; the ball start
    has the requested packing fraction; both are functions of (seed, gid) only."""
    import numpy as np
    from mpipack.engine import initial as init
    s = config.load("default", ["n=8000", "init.sigma=auto"])
    assert init.gaussian_sigma(s) == pytest.approx(2.0, rel=1e-15)  # (8000/2000)^(1/2)
    s3 = config.load("default", ["n=16000", "dim=3", "init.sigma=auto"])
    assert init.gaussian_sigma(s3) == pytest.approx(2.0, rel=1e-12)
    b = config.load("default", ["n=4000", "init.kind=ball", "init.fraction=0.5"])
    R = init.ball_radius(b)
    assert 4000 * (math.pi / 4) == pytest.approx(0.5 * math.pi * R * R, rel=1e-12)
    x = init.positions(b, np.arange(4000, dtype=np.int64))
    r = np.sqrt((x ** 2).sum(axis=1))
    assert r.max() <= R and r.max() > 0.99 * R
    assert np.mean(r < R / 2) == pytest.approx(0.25, abs=0.03)  # uniform in area
    part = init.positions(b, np.arange(1000, 3000, dtype=np.int64))
    assert np.array_equal(part, x[1000:3000])


def test_schedule_follows_what_the_scene_sets(tmp_path):
    """Defaults that work wherever a key is left out: a DAHA scene that sets none of alpha,
    beta, gamma, c gets the fire-al schedule and the certified stop; one that sets any of them
    gets the fixed scheme (the paper's values for the rest, gamma = sqrt(alpha beta))."""
    f = tmp_path / "only-n.toml"
    f.write_text("n = 500\n")
    s = config.load(str(f))
    assert s.method.schedule == "fire-al" and s.stop.rule == "certified"
    assert (s.method.alpha, s.method.beta, s.method.gamma, s.method.c) == (None, None, None, None)
    assert config.from_dict(s.as_dict()) == s
    s = config.load(str(f), ["method.alpha=0.01"])
    assert s.method.schedule == "fixed" and s.stop.rule == "eps"
    assert (s.method.beta, s.method.c) == (2.8e3, 2.0)
    assert s.method.gamma == pytest.approx(math.sqrt(0.01 * 2.8e3), rel=1e-15)
    assert config.load(None, ["method.name=nap"]).method.schedule == "fixed"
    # the fixed scheme with nothing set: the paper's whole set, not gamma = sqrt(7.8e-3 2.8e3)
    m = config.load(None, ["method.schedule=fixed"]).method
    assert (m.alpha, m.beta, m.gamma, m.c) == (7.8e-3, 2.8e3, 1.6e-2, 2.0)
    assert config.load(None, ["stop.rule=eps"]).stop.rule == "eps"  # an explicit rule stays
    for over, key in ((["method.schedule=fire-al", "method.c=3"], "method.c"),
                      (["method.schedule=fire-al", "method.name=aha"], "method.schedule"),
                      (["method.schedule=adaptive"], "method.schedule")):
        with pytest.raises(config.SceneError, match=key):
            config.load(None, over)
