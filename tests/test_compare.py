"""``mpipack compare``: work-precision diagrams (PNG, CSV, markdown) from real runs recording
metrics.csv, the quick form end to end, a peer code's curve, and bad input."""

import csv
import subprocess
import sys

from conftest import describe, mpi_env


def cli(args, cwd, timeout=600):
    return subprocess.run([sys.executable, "-m", "mpipack.cli"] + [str(a) for a in args], cwd=str(cwd),
                          env=mpi_env(), capture_output=True, text=True, timeout=timeout)


def test_compare_quick(tmp_path):
    out = tmp_path / "cmp"
    proc = cli(["compare", "--quick", "--out", out], tmp_path)
    assert proc.returncode == 0, describe(proc)
    md = (out / "compare.md").read_text()
    for n in (7, 100):
        png = out / f"work_precision_paper-2d_n{n}.png"
        assert png.stat().st_size > 30000, png
        assert png.name in md
    # the paper's five methods and the scene's own, two tolerances, two scenes
    for m in ("DAHA-S", "DAHA-NS", "NAP-NS", "NAP-S", "NAV-NS", "scene DAHA-S"):
        assert md.count(f"| {m} | ") == 4, (m, md)
    with open(out / "ladder.csv") as f:
        ladder = list(csv.DictReader(f))
    assert len(ladder) == 2 * 6 * 2 * 2
    # N = 7: the known optimum W = 3; the paper's methods reach it (Table 1 orders)
    rows = [r for r in ladder if r["n"] == "7" and r["eps"] == "1e-06" and not r["method"].startswith("scene")]
    assert all(float(r["W_err"]) < 1e-4 for r in rows), rows
    with open(out / "curves.csv") as f:
        curves = list(csv.DictReader(f))
    assert len({(r["n"], r["method"], r["seed"]) for r in curves}) == 2 * 6 * 2


def test_compare_with_a_peer_curve(tmp_path):
    """A peer code's CSV (here: made from mpipack's own curve, relabelled) joins the picture."""
    out = tmp_path / "a"
    base = ["compare", "paper-2d", "--set", "n=7", "--methods", "DAHA-NS,NAP-NS:alpha=0.5", "--tolerances", "1e-4",
            "--seeds", "1"]
    proc = cli(base + ["--out", out], tmp_path)
    assert proc.returncode == 0, describe(proc)
    with open(out / "curves.csv") as f:
        rows = [r for r in csv.DictReader(f) if r["method"] == "DAHA-NS"]
    peer = tmp_path / "peer.csv"
    with open(peer, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["label", "seed", "n", "wall_seconds", "work", "max_overlap", "A", "W", "kkt_residual"])
        for r in rows:
            w.writerow(["PEER", 1, 7, float(r["seconds"]) * 3, float(r["work"]) * 2, r["max_overlap"], "", r["W"], ""])
    proc = cli(base + ["--out", tmp_path / "b", "--peer", peer], tmp_path)
    assert proc.returncode == 0, describe(proc)
    with open(tmp_path / "b" / "curves.csv") as f:
        got = [r for r in csv.DictReader(f) if r["method"] == "PEER"]
    assert len(got) == len(rows) and float(got[-1]["work"]) == 2 * float(rows[-1]["work"])
    assert "NAP-NS:alpha=0.5" in (tmp_path / "b" / "compare.md").read_text()


def test_compare_bad_input(tmp_path):
    for args, word in ((["--methods", "FOO-S"], "FOO-S"), (["--methods", "DAHA-X"], "DAHA-X"),
                       (["--tolerances", "0,1e-4"], "--tolerances"), (["--seeds", "a"], "--seeds"),
                       (["--peer", tmp_path / "nope.csv"], "nope.csv"), (["--set", "n=0"], "'n'")):
        proc = cli(["compare", "paper-2d"] + args + ["--out", tmp_path / "x"], tmp_path, timeout=120)
        assert proc.returncode == 2, describe(proc)
        lines = [line for line in proc.stderr.splitlines() if line.strip()]
        assert len(lines) == 1 and lines[0].startswith("mpipack: error:") and word in lines[0], describe(proc)


def test_a_damaged_peer_file_is_one_line(tmp_path):
    """A binary file (UnicodeDecodeError before), a CSV of another format (silently ignored,
    exit 0 before) and a bad number: one line naming the file, exit 2, before any run."""
    binary = tmp_path / "peer.bin"
    binary.write_bytes(b"\x00\x01\xff\xfe binary")
    other = tmp_path / "other.csv"
    other.write_text("a,b\n1,2\n")
    bad = tmp_path / "bad.csv"
    bad.write_text("label,seed,n,wall_seconds,work,max_overlap\nX,1,7,fast,10,0.1\n")
    for f, words in ((binary, "not a text file"), (other, "not a curve"), (bad, "line 2")):
        proc = cli(["compare", "--quick", "--peer", f, "--out", tmp_path / "cmp"], tmp_path, timeout=120)
        assert proc.returncode == 2, describe(proc)
        lines = [line for line in proc.stderr.splitlines() if line.strip()]
        assert len(lines) == 1 and str(f) in lines[0] and words in lines[0], describe(proc)
