"""numba's on-disk cache filled by several processes at once (mpipack.jit).

The ranks of one job compile the same functions into one cache folder at the same moment. Two
saves of two different signatures of one function may interleave in any order; afterwards
every key the index holds must load that key's own code, never another's. numba's numbered
data files fail this (the check below finds the interleaving); mpipack.jit's names by key do not.
"""

import itertools
import os
import re
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from mpipack import jit  # noqa: F401  (installs the cache's save)
from numba.core import caching

REPO = Path(__file__).resolve().parents[1]
KEYS = {"a": ("(int64,)", ("x86_64", "host", ""), ("bytecode", "cells")),
        "b": ("(Literal[int](3),)", ("x86_64", "host", ""), ("bytecode", "cells"))}
STEPS = 3  # each save: one index read and two writes (data, index), in its own order


class Turnstile:
    """Lets the two saves' steps through one at a time, in a given order of 'a' and 'b'."""

    def __init__(self, order):
        self.order, self.position = order, 0
        self.turn = threading.Condition()

    def step(self, who, call, *args):
        with self.turn:
            if not self.turn.wait_for(lambda: self.order[self.position] == who, timeout=10):
                raise TimeoutError(f"step {self.position} of {self.order} never came")
            try:
                return call(*args)
            finally:
                self.position += 1
                self.turn.notify_all()


def race(save, folder, order):
    """Two processes save keys a and b of one function with their steps interleaved as `order`;
    returns what a third process then loads for each key (None: a cache miss)."""
    turnstile = Turnstile(order)
    threads = []
    for who in "ab":
        cache_file = caching.IndexDataCacheFile(str(folder), "kernel-12.py311", "stamp")
        for step in ("_load_index", "_save_data", "_save_index"):
            call = getattr(cache_file, step)
            setattr(cache_file, step, lambda *a, call=call, who=who: turnstile.step(who, call, *a))
        payload = f"machine code of {who}".encode()
        threads.append(threading.Thread(target=save, args=(cache_file, KEYS[who], payload)))
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=20)
        assert not t.is_alive(), f"a save hung on {order}"
    reader = caching.IndexDataCacheFile(str(folder), "kernel-12.py311", "stamp")
    return {who: reader.load(KEYS[who]) for who in "ab"}


ORDERS = sorted(set(itertools.permutations("aaabbb")))


def wrong_loads(save, tmp_path):
    """The interleavings after which a key loads the other key's code."""
    bad = []
    for i, order in enumerate(ORDERS):
        folder = tmp_path / f"race{i}"
        folder.mkdir()
        loaded = race(save, folder, order)
        for who in "ab":
            if loaded[who] is not None and loaded[who] != f"machine code of {who}".encode():
                bad.append(("".join(order), who))
    return bad


def test_no_interleaving_of_two_saves_loads_the_wrong_code(tmp_path):
    assert len(ORDERS) == 20
    assert wrong_loads(caching.IndexDataCacheFile.save, tmp_path) == []


def test_numbas_numbered_files_do_load_the_wrong_code(tmp_path):
    """The check above can fail: numba's own save, under the same interleavings, maps a key to
    the other key's file. (If a numba release passes this, mpipack.jit's change can go.)"""
    assert caching.IndexDataCacheFile.save is jit._save
    assert wrong_loads(jit._numbered_save, tmp_path) != []


def test_saved_one_after_the_other_both_keys_load(tmp_path):
    loaded = race(caching.IndexDataCacheFile.save, tmp_path, tuple("aaabbb"))
    assert loaded == {"a": b"machine code of a", "b": b"machine code of b"}


def test_a_real_function_is_cached_under_key_names_and_loaded_again(tmp_path):
    """End to end with numba: one process compiles two signatures into a fresh cache folder,
    a second loads both from it (cache hits, the right results, no compilation)."""
    (tmp_path / "probe_kernel.py").write_text(
        "from mpipack.jit import njit\n\n@njit(cache=True)\ndef twice(x):\n    return 2 * x\n")
    script = ("import sys; sys.path.insert(0, sys.argv[1]); import probe_kernel as p\n"
              "print(p.twice(3), p.twice(1.25), sum(p.twice.stats.cache_hits.values()))\n")
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "cache"),
               PYTHONPATH=f"{REPO}{os.pathsep}{os.environ.get('PYTHONPATH', '')}")
    runs = [subprocess.run([sys.executable, "-c", script, str(tmp_path)], env=env, capture_output=True,
                           text=True, timeout=120) for _ in range(2)]
    for r in runs:
        assert r.returncode == 0, r.stderr
    assert runs[0].stdout.split() == ["6", "2.5", "0"]
    assert runs[1].stdout.split() == ["6", "2.5", "2"]
    files = sorted(p.name for p in (tmp_path / "cache").rglob("*.nbc"))
    assert len(files) == 2 and all(re.fullmatch(r"probe_kernel\.twice-\d+\.py\d+\.[0-9a-f]{16}\.nbc", f)
                                   for f in files), files
