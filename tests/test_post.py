"""``mpipack post`` and ``mpipack.post``: each measure against a packing with a known answer
(a hexagonal patch, an FCC block, a simple cubic block, two touching spheres, a 1D chain, a
uniform cloud for g(r)), a real run's values in their known ranges, the same numbers on 1, 2
and 3 ranks, and one-line errors (exit 2) for files that cannot be used."""

import json
import math
import subprocess
import sys

import numpy as np
import pytest

from conftest import describe, mpirun
from mpipack import post

HEX_DENSITY = math.pi / (2 * math.sqrt(3))
FCC_DENSITY = math.pi / (3 * math.sqrt(2))
Q6_FCC = 0.5745     # Steinhardt, Nelson and Ronchetti 1983, 12 neighbours
Q6_SC = 0.3536      # 6 neighbours on the axes


def hex_patch(radius):
    """Unit discs of a hexagonal lattice (touching) within ``radius`` of the origin."""
    k = int(radius) + 2
    a, b = np.meshgrid(np.arange(-2 * k, 2 * k + 1), np.arange(-2 * k, 2 * k + 1))
    x = np.stack([a + 0.5 * b, b * math.sqrt(3) / 2], axis=-1).reshape(-1, 2)
    return x[(x ** 2).sum(axis=1) <= radius ** 2]


def fcc_ball(radius):
    """Unit spheres of an FCC lattice (touching, nearest distance 1) within ``radius``."""
    k = int(radius) + 2
    g = np.arange(-k, k + 1)
    cube = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3).astype(float)
    basis = np.array([[0, 0, 0], [0.5, 0.5, 0], [0.5, 0, 0.5], [0, 0.5, 0.5]])
    x = (cube[:, None, :] + basis[None, :, :]).reshape(-1, 3) * math.sqrt(2)
    return x[(x ** 2).sum(axis=1) <= radius ** 2]


def sc_ball(radius):
    k = int(radius) + 1
    g = np.arange(-k, k + 1)
    x = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3).astype(float)
    return x[(x ** 2).sum(axis=1) <= radius ** 2]


def interior(x, margin):
    r = np.sqrt(((x - x.mean(axis=0)) ** 2).sum(axis=1))
    return r <= r.max() - margin


# ---- known answers, on arrays ----------------------------------------------------------------

def test_hexagonal_patch():
    x = hex_patch(20.0)
    d = np.ones(len(x))
    radii = np.linspace(4.0, 14.0, 11)
    phi = post.density_profile(x, d, radii)
    assert np.all(np.abs(phi - HEX_DENSITY) < 0.01 * HEX_DENSITY), phi
    counts = post.neighbour_counts(x, d)
    inside = interior(x, 1.5)
    assert np.all(counts[inside] == 6) and counts.max() == 6 and counts.min() >= 2
    psi = post.hexatic(x, d)
    assert np.allclose(np.abs(psi), 1.0, atol=1e-12)
    z = post.contact_numbers(x, d)
    assert z["rattlers"] == 0 and z["Z"] == pytest.approx(counts.mean())


def test_fcc_block():
    x = fcc_ball(7.0)
    d = np.ones(len(x))
    phi = post.density_profile(x, d, np.linspace(2.5, 5.0, 6))
    assert np.all(np.abs(phi - FCC_DENSITY) < 0.02 * FCC_DENSITY), phi
    counts = post.neighbour_counts(x, d)
    inside = interior(x, 1.5)
    assert np.all(counts[inside] == 12) and counts.max() == 12
    q6, q6bar = post.steinhardt_q6(x, d)
    assert np.allclose(q6[inside], Q6_FCC, atol=1e-4)
    assert np.allclose(q6bar[interior(x, 3.0)], Q6_FCC, atol=1e-4)  # every neighbour has 12 too


def test_simple_cubic_block():
    x = sc_ball(6.0)
    d = np.ones(len(x))
    phi = post.density_profile(x, d, np.linspace(2.5, 4.0, 4))
    assert np.all(np.abs(phi - math.pi / 6) < 0.03 * math.pi / 6), phi
    counts = post.neighbour_counts(x, d)
    inside = interior(x, 1.5)
    assert np.all(counts[inside] == 6)
    q6, _ = post.steinhardt_q6(x, d)
    assert np.allclose(q6[inside], Q6_SC, atol=1e-4)


def test_two_touching_spheres():
    x = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    d = np.ones(2)
    assert post.neighbour_counts(x, d).tolist() == [1, 1]
    z = post.contact_numbers(x, d)
    assert z["Z"] == 1.0 and z["rattlers"] == 2   # fewer than b + 1 = 4 contacts each
    apart = np.array([[0.0, 0.0, 0.0], [1.01, 0.0, 0.0]])
    assert post.contact_numbers(apart, d)["Z"] == 0.0
    assert post.neighbour_counts(apart, d).tolist() == [1, 1]   # 1.01 < 1.1 d
    # the covered fraction of a ball about the centre that holds both spheres whole
    R = 2.0
    assert post.density_profile(x, d, [R])[0] == pytest.approx(2 * (math.pi / 6) / (4 / 3 * math.pi * R ** 3))


def test_one_dimensional_chain():
    x = np.arange(101, dtype=float)[:, None]
    d = np.ones(101)
    phi = post.density_profile(x, d, [5.0, 20.0, 50.0])
    assert np.allclose(phi, 1.0)
    counts = post.neighbour_counts(x, d)
    assert counts[0] == counts[-1] == 1 and np.all(counts[1:-1] == 2)


def test_pair_distribution_of_a_uniform_cloud_is_one():
    """Points uniform in a disc (tiny diameters): g(r) = 1 within the noise, with interior
    centres and the bulk density."""
    rng = np.random.default_rng(3)
    n = 40000
    r = 60.0 * np.sqrt(rng.uniform(size=n))
    t = rng.uniform(0, 2 * np.pi, size=n)
    x = np.stack([r * np.cos(t), r * np.sin(t)], axis=1)
    rr, g = post.pair_distribution(x, np.full(n, 0.01), 5.0, bins=10, r_bulk=55.0)
    assert np.all(np.abs(g[2:] - 1.0) < 0.05), g


def test_pair_distribution_of_the_hexagonal_patch():
    x = hex_patch(25.0)
    r, g = post.pair_distribution(x, np.ones(len(x)), 2.2, bins=44)
    peaks = r[g > 1.0]
    # shells at 1, sqrt(3), 2 diameters
    for shell in (1.0, math.sqrt(3), 2.0):
        assert np.any(np.abs(peaks - shell) < 0.05), (shell, peaks)
    assert np.all(g[r < 0.95] == 0)


# ---- files and the command -----------------------------------------------------------------

def write_snapshot(path, x, diam, iteration=7, extra=None):
    from mpipack.io import SnapshotWriter
    from mpipack.parallel.comm import Comm
    n, dim = x.shape
    with SnapshotWriter(Comm.serial(), str(path), n, dim, {"scene": "{}"}, xdmf=False) as w:
        w.write(np.arange(n), {"position": x, "diameter": diam, **(extra or {})},
                {"iteration": iteration})


def post_cli(args, cwd, ranks=None, timeout=300):
    if ranks is None:
        cmd = [sys.executable, "-m", "mpipack.cli", "post"] + [str(a) for a in args]
        from mpipack.parallel.launcher import mpi_env
        return subprocess.run(cmd, cwd=str(cwd), env=mpi_env(), capture_output=True, text=True, timeout=timeout)
    return mpirun(ranks, [sys.executable, "-m", "mpipack.cli", "post"] + list(args), cwd, timeout=timeout)


def summaries(folder, names):
    return {m: json.loads((folder / f"{m}.json").read_text())["summary"] for m in names}


@pytest.mark.mpi
def test_fcc_file_gives_the_same_numbers_on_1_2_3_ranks(tmp_path):
    x = fcc_ball(6.0)
    n = len(x)
    rng = np.random.default_rng(1)
    write_snapshot(tmp_path / "fcc.h5", x, np.ones(n),
                   extra={"pressure": rng.uniform(0.5, 2.0, n), "contacts": np.full(n, 12, np.int32)})
    got = {}
    names = ("density", "neighbours", "contacts", "pressure", "gr", "order")
    for ranks in (1, 2, 3):
        out = tmp_path / f"post{ranks}"
        p = post_cli(["all", "fcc.h5", "--out", out, "--r-max", "2.5", "--bins", "99"], tmp_path, ranks=ranks)
        assert p.returncode == 0, describe(p)
        got[ranks] = summaries(out, names)
        for name in names:
            assert (out / f"{name}.png").stat().st_size > 1000
            assert (out / f"{name}.csv").read_text() == (tmp_path / "post1" / f"{name}.csv").read_text()
    assert got[1] == got[2] == got[3]
    s = got[1]
    assert abs(s["density"]["plateau"] - FCC_DENSITY) < 0.02 * FCC_DENSITY
    assert s["neighbours"]["max"] == 12
    assert s["order"]["crystalline_share"] > 0.5
    assert s["gr"]["first_peak_r"] == pytest.approx(1.0, abs=0.02)
    assert s["contacts"]["by_gap"]["Z"] == pytest.approx(s["neighbours"]["mean"])


@pytest.mark.mpi
def test_a_real_run_in_its_known_ranges_on_1_2_3_ranks(run_mpipack, tmp_path):
    proc, summary, _ = run_mpipack(2, sets=["n=600", "dim=3"], tag="run3d")
    assert proc.returncode == 0, describe(proc)
    run = tmp_path / "run3d" / "out"
    names = ("density", "neighbours", "contacts", "pressure", "gr", "order")
    got = {}
    for ranks in (1, 2, 3):
        p = post_cli(["all", run, "--out", tmp_path / f"p{ranks}"], tmp_path, ranks=ranks)
        assert p.returncode == 0, describe(p)
        assert "warning" not in p.stdout, p.stdout
        got[ranks] = summaries(tmp_path / f"p{ranks}", names)
    assert got[1] == got[2] == got[3]
    s = got[1]
    # a random close packing of a small 3D cluster (the paper's Fig. 10: 0.64-0.66, 8-10 neighbours)
    assert 0.60 < s["density"]["plateau"] < 0.70
    assert s["density"]["density_at_gyration_radius"] == pytest.approx(summary["density"], rel=1e-12)
    assert 7.0 < s["neighbours"]["mean"] < 10.0 and s["neighbours"]["share_8_to_10"] > 0.4
    assert 5.0 < s["contacts"]["by_multiplier"]["Z"] < 7.0
    assert abs(s["contacts"]["by_gap"]["isostaticity"]) < 1.0   # jammed: Z ~ 2b without rattlers
    assert s["pressure"]["mean"] > 0 and s["order"]["crystalline_share"] < 0.2


def test_convergence_and_compare(run_mpipack, tmp_path):
    runs = []
    for seed in (1, 2, 3):
        proc, _, _ = run_mpipack(1, sets=["n=300", f"seed={seed}", "output.metrics_every=50"], tag=f"s{seed}")
        assert proc.returncode == 0, describe(proc)
        runs.append(tmp_path / f"s{seed}" / "out")
    p = post_cli(["convergence", runs[0]], tmp_path)
    assert p.returncode == 0, describe(p)
    conv = json.loads((runs[0] / "post" / "convergence.json").read_text())
    assert conv["rows"] >= 2 and conv["last"]["max_overlap"] <= 1e-3
    p = post_cli(["compare"] + runs + ["--out", tmp_path / "cmp"], tmp_path, ranks=2)
    assert p.returncode == 0, describe(p)
    doc = json.loads((tmp_path / "cmp" / "compare.json").read_text())
    assert len(doc["runs"]) == 3
    plateaus = [r["density.plateau"] for r in doc["runs"]]
    assert doc["statistics"]["density.plateau"]["mean"] == pytest.approx(np.mean(plateaus))
    assert len(set(plateaus)) == 3   # three seeds, three packings
    for one, run in zip(doc["runs"], runs):  # the same numbers as a one-run post
        p = post_cli(["density", run], tmp_path)
        assert p.returncode == 0, describe(p)
        assert json.loads((run / "post" / "density.json").read_text())["summary"]["plateau"] == one["density.plateau"]
    assert (tmp_path / "cmp" / "compare-density.png").stat().st_size > 1000
    assert "| density.plateau |" in p.stdout or "density.plateau" in (tmp_path / "cmp" / "compare.csv").read_text()


def test_an_unconverged_snapshot_is_flagged(run_mpipack, tmp_path):
    proc, _, _ = run_mpipack(1, sets=["n=300", "stop.max_iter=50"], tag="short")
    assert proc.returncode == 4, describe(proc)
    p = post_cli(["density", tmp_path / "short" / "out"], tmp_path)
    assert p.returncode == 0, describe(p)
    assert "warning: the run did not converge" in p.stdout
    doc = json.loads((tmp_path / "short" / "out" / "post" / "density.json").read_text())
    assert doc["warnings"]


@pytest.mark.parametrize("case", ["nan", "missing", "foreign", "truncated", "iteration", "nothing", "option",
                                  "damaged"])
def test_unusable_input_is_one_line_and_exit_2(tmp_path, case):
    x = hex_patch(5.0)
    d = np.ones(len(x))
    f = tmp_path / "s.h5"
    args = ["density", f]
    if case == "nan":
        x[3, 1] = np.nan
        write_snapshot(f, x, d)
    elif case == "missing":
        write_snapshot(f, x, d)
        import h5py
        with h5py.File(f, "r+") as h:
            del h["snapshots"][sorted(h["snapshots"])[-1]]["diameter"]
    elif case == "foreign":
        import h5py
        with h5py.File(f, "w") as h:
            h["x"] = np.zeros(3)
    elif case == "truncated":
        write_snapshot(f, x, d)
        data = f.read_bytes()
        f.write_bytes(data[: len(data) // 2])
    elif case == "iteration":
        write_snapshot(f, x, d)
        args += ["--iteration", "99"]
    elif case == "nothing":
        args = ["density", tmp_path / "no-such-run"]
    elif case == "option":
        write_snapshot(f, x, d)
        args += ["--factor", "-1"]
    elif case == "damaged":  # one bit of one diameter, in place: only the checksum sees it
        write_snapshot(f, x, d)
        import h5py
        with h5py.File(f, "r+") as h:
            ds = h["snapshots"][sorted(h["snapshots"])[-1]]["diameter"]
            v = ds[()]
            v[4] = np.nextafter(v[4], 2.0)
            ds[...] = v
        from mpipack import read_snapshot
        from mpipack.io import SnapshotError
        with pytest.raises(SnapshotError, match="damaged snapshot 7: diameter does not match its checksum"):
            read_snapshot(str(f))
        from mpipack.parallel.launcher import mpi_env
        v = subprocess.run([sys.executable, "-m", "mpipack.cli", "vtk", str(f)], cwd=str(tmp_path), env=mpi_env(),
                           capture_output=True, text=True, timeout=300)
        assert v.returncode == 2 and v.stderr.count("\n") == 1 and "damaged snapshot 7" in v.stderr, describe(v)
    p = post_cli(args, tmp_path)
    assert p.returncode == 2, describe(p)
    lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("mpipack: error: "), p.stderr
    assert "Traceback" not in p.stderr


def test_rattlers_excluded_on_request(tmp_path):
    """A hexagonal patch and one disc far away: the loose disc is a rattler; --exclude-rattlers
    leaves it (and any other rattler) out of the neighbour histogram and the order means."""
    x = np.vstack([hex_patch(8.0), [[40.0, 0.0]]])
    n = len(x)
    write_snapshot(tmp_path / "s.h5", x, np.ones(n))
    a = post.analyse(str(tmp_path / "s.h5"))
    every = a.neighbours()
    assert every.summary["spheres"] == n and every.table["spheres"][0] == 1
    kept = a.neighbours(exclude_rattlers=True)
    assert kept.table["spheres"][0] == 0 and kept.summary["spheres"] < n
    _, rattlers = a.contacts()
    assert n - 1 in rattlers and kept.summary["spheres"] == n - len(rattlers)
    assert a.order(exclude_rattlers=True).summary["mean_abs_psi6"] == pytest.approx(1.0, abs=1e-12)
