"""Size distributions (``particles.distribution``): each law's diameters against its moments,
exact counts for a discrete mixture, one-line errors for bad keys, the same packing on 1, 2 and
3 ranks, the built-in bidisperse and lognormal scenes certified, and old checkpoints (whose
scene has no distribution keys) still restart."""

import math

import numpy as np
import pytest

from conftest import assert_bitwise_equal, describe
from mpipack import config
from mpipack.engine import initial


def diameters_of(*sets, n=200000):
    scene = config.load(None, list(sets) + [f"n={n}"])
    return scene, initial.scene_diameters(scene, np.arange(scene.n))


@pytest.mark.parametrize("law,spread", [("normal", 0.2), ("lognormal", 0.3), ("lognormal", 1.0)])
def test_normal_and_lognormal_laws(law, spread):
    scene, d = diameters_of(f"particles.distribution={law}", f"particles.spread={spread}",
                            "particles.diameter=2.0")
    p = scene.particles
    assert d.min() > 0 and d.max() <= p.d_max
    # the sample's moments converge to the distribution's (truncated at 3 standard deviations)
    assert d.mean() == pytest.approx(p.d_mean, rel=3 * spread / math.sqrt(len(d)) * 3)
    assert ((d / 2) ** 3).mean() == pytest.approx(p.mean_radius_power(3), rel=0.01)
    if law == "normal":
        assert p.d_mean == pytest.approx(2.0, rel=1e-12) and p.d_max == pytest.approx(2.0 * (1 + 3 * spread))
        assert d.std() / d.mean() == pytest.approx(spread * 0.9866, rel=0.02)  # the truncated law's spread
    else:  # ln d is a truncated normal of standard deviation sqrt(ln(1 + spread^2))
        s = math.sqrt(math.log1p(spread ** 2))
        assert np.log(d).std() == pytest.approx(s * 0.9866, rel=0.02)
        assert np.log(p.d_max) - np.log(d.min()) <= 6 * s + 1e-9


def test_discrete_mixture_in_exact_counts():
    scene, d = diameters_of("particles.distribution=discrete", "particles.sizes=[1.0, 1.4, 2.0]",
                            "particles.fractions=[3, 2, 1]", n=6001)
    counts = {float(s): int(c) for s, c in zip(*np.unique(d, return_counts=True))}
    # gids [0, rint(N/2)) have size 1, [rint(N/2), rint(5N/6)) 1.4, the rest 2: 3000, 2001, 1000
    assert counts == {1.0: 3000, 1.4: 2001, 2.0: 1000}
    assert np.all(d[:3000] == 1.0) and np.all(d[3000:5001] == 1.4) and np.all(d[5001:] == 2.0)
    p = scene.particles
    assert p.d_max == 2.0 and p.d_mean == pytest.approx((3 * 1.0 + 2 * 1.4 + 1 * 2.0) / 6)


def test_the_default_laws_are_unchanged():
    """uniform and mono: the same draws and the same length unit as before the distributions."""
    scene, d = diameters_of("particles.diameter_max=3.0", n=1000)
    assert np.array_equal(d, initial.diameters(scene.seed, np.arange(1000), 1.0, 3.0))
    assert scene.particles.d_mean == 2.0 and scene.particles.d_max == 3.0
    scene, d = diameters_of(n=10)
    assert np.all(d == 1.0) and scene.particles.distribution == "uniform"


@pytest.mark.parametrize("sets,words", [
    (["particles.distribution=lognormal"], "needs particles.spread"),
    (["particles.distribution=normal", "particles.spread=0.4"], "below 1/3"),
    (["particles.distribution=gamma"], "must be one of"),
    (["particles.distribution=lognormal", "particles.spread=0.2", "particles.diameter_max=3"], "does not apply"),
    (["particles.distribution=discrete", "particles.sizes=[1.0]", "particles.fractions=[0.5, 0.5]"],
     "same length"),
    (["particles.distribution=discrete", "particles.sizes=[1.0, -1]", "particles.fractions=[1, 1]"],
     "positive numbers"),
    (["particles.spread=0.2"], "does not apply"),
])
def test_bad_distribution_keys(sets, words):
    with pytest.raises(config.SceneError, match=words):
        config.load(None, sets)


def test_an_old_checkpoints_scene_restarts():
    """A scene table written before the distribution keys existed holds the defaults."""
    new = config.load(None, []).as_dict()
    old = {**new, "particles": {"diameter": 1.0, "diameter_max": None}}
    assert config.physics_changes(old, new) == []
    changed = config.load(None, ["particles.distribution=mono"]).as_dict()
    assert config.physics_changes(old, changed) == ["particles.distribution ('uniform' -> 'mono')"]


@pytest.mark.mpi
@pytest.mark.parametrize("scene,sets", [("bidisperse-2d", ["n=300"]), ("lognormal-3d", ["n=200"])])
def test_the_same_packing_on_1_2_3_ranks(run_mpipack, scene, sets):
    ref = None
    for ranks in (1, 2, 3):
        proc, summary, dump = run_mpipack(ranks, scene=scene, sets=sets, dump=True)
        assert proc.returncode == 0, describe(proc)
        assert summary["converged"] is True
        if ref is None:
            ref = dump
            d = dump["diam"]
            if scene == "bidisperse-2d":
                assert sorted(np.unique(d).tolist()) == [1.0, 1.4] and (d == 1.0).sum() == 150
            else:
                assert len(np.unique(d)) == len(d)
        else:
            assert_bitwise_equal(ref, dump, f"{scene} on {ranks} ranks")
