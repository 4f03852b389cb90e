"""The library API (``mpipack.run``, ``load_scene``, ``read_snapshot``): the README's example as
written, on 1, 2 and 3 ranks, and what a library caller relies on (no files without ``out``,
keyword overrides, one-line errors, the same result as ``mpipack run``)."""

import json
import re
import sys

import numpy as np
import pytest

from conftest import REPO, describe, mpipack_run, mpirun

pytestmark = pytest.mark.mpi


def readme_example():
    """The README's library-API code block, verbatim."""
    text = (REPO / "README.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, flags=re.S)
    assert blocks, "the README has no python example"
    return blocks[0]


@pytest.mark.parametrize("ranks", [1, 2, 3])
def test_the_readme_example_runs_on_any_rank_count(tmp_path, ranks):
    script = tmp_path / "example.py"
    script.write_text(readme_example() + "\n"
                      "import json\n"
                      "json.dump({'converged': result.converged, 'iterations': result.iterations,\n"
                      "           'W': result.figures['W'], 'exit': result.exit_code,\n"
                      "           'snap_iteration': snap.iteration, 'shape': list(snap.position.shape),\n"
                      "           'files': result.files},\n"
                      "          open(f'out-{__import__(\"mpi4py\").MPI.COMM_WORLD.Get_rank()}.json', 'w'))\n")
    proc = mpirun(ranks, [sys.executable, str(script)], tmp_path)
    assert proc.returncode == 0, describe(proc)
    if ranks == 1:  # the example prints converged, iterations and the KKT residual (every rank)
        first = proc.stdout.splitlines()[0].split()
        assert first[0] == "True" and int(first[1]) > 0 and float(first[2]) <= 1e-2, describe(proc)
    got = [json.loads((tmp_path / f"out-{r}.json").read_text()) for r in range(ranks)]
    assert all(g == got[0] for g in got), got  # every rank returns the same Result
    g = got[0]
    assert g["converged"] and g["exit"] == 0 and g["shape"] == [500, 2] and g["snap_iteration"] == g["iterations"]
    assert (tmp_path / "my-run" / "summary.json").exists()
    summary = json.loads((tmp_path / "my-run" / "summary.json").read_text())
    assert summary["ranks"] == ranks and summary["iterations"] == g["iterations"] and summary["W"] == g["W"]


def test_a_library_run_matches_the_command_line_bit_for_bit(tmp_path, monkeypatch):
    import mpipack
    monkeypatch.chdir(tmp_path)
    res = mpipack.run("default", seed=3, n=300, gather=True)
    (tmp_path / "cli").mkdir()
    proc, summary, dump = mpipack_run(1, tmp_path / "cli", sets=["n=300"], extra=["--seed", "3"], dump=True)
    assert proc.returncode == 0, describe(proc)
    assert res.iterations == summary["iterations"] and res.figures["W"] == summary["W"]
    assert np.array_equal(res.particles["x"], dump["x"])
    assert np.array_equal(res.particles["pairs_lambda"], dump["pairs_lambda"])
    # no out: nothing written, not even a summary
    assert res.files == [] and not (tmp_path / "mpipack-out").exists()


def test_keyword_overrides_and_options(tmp_path):
    import mpipack
    res = mpipack.run("paper-2d", n=200, stop__max_iter=30, options={"stop.eps": 0.0})
    assert res.iterations == 30 and res.stop_reason == "max_iter" and res.exit_code == 0
    assert res.summary["resolved_scene"]["n"] == 200
    scene = mpipack.load_scene("paper-2d", overrides=["n=200"], stop__max_iter=40)
    assert (scene.n, scene.stop.max_iter) == (200, 40)


def test_bad_input_is_one_line(tmp_path, capsys):
    import mpipack
    from mpipack import config
    with pytest.raises(config.SceneError, match="unknown key 'stop.bogus'"):
        mpipack.load_scene(None, stop__bogus=1)
    res = mpipack.run(None, options={"n": -5})
    assert res.exit_code == 2 and "n" in res.error and not res.converged
    assert capsys.readouterr().err.strip().count("\n") == 0  # one line


def test_read_snapshot_takes_a_folder_or_a_file_and_an_iteration(tmp_path):
    import mpipack
    out = tmp_path / "run"
    res = mpipack.run("default", n=100, out=str(out), output__snapshot_every=50)
    assert res.converged
    last = mpipack.read_snapshot(str(out))
    first = mpipack.read_snapshot(str(out / "snapshots.h5"), iteration=50)
    assert last.iteration == res.iterations and first.iteration == 50
    assert last.position.shape == (100, 2) and last.diameter.shape == (100,)
    assert not np.array_equal(first.position, last.position)
    with pytest.raises(FileNotFoundError):
        mpipack.read_snapshot(str(tmp_path / "nothing"))
