"""The drivers keep freed memory for reuse (glibc's mmap and trim thresholds)."""

import platform

import numpy as np
import pytest
from dask.system import CPU_COUNT

import streamsvd._util.malloc as malloc
from streamsvd.parallel import tall as parallel
from streamsvd.parallel import tree as parallel_tree


@pytest.fixture
def fresh(monkeypatch):
    """A process where the thresholds were not tried yet, with malloc untuned."""
    monkeypatch.setattr(malloc, "_applied", None)
    for name in malloc._USER_SETTINGS:
        monkeypatch.delenv(name, raising=False)
    monkeypatch.delenv("GLIBC_TUNABLES", raising=False)
    calls = []

    def mallopt(param, value):
        calls.append((param, value))
        return 1

    monkeypatch.setattr(malloc, "_glibc_mallopt", lambda: mallopt)
    return calls


def test_both_thresholds_and_the_arenas_are_set_once(fresh):
    assert malloc.keep_freed_memory() and malloc.keep_freed_memory()
    assert fresh == [(malloc._M_MMAP_THRESHOLD, malloc.MMAP_THRESHOLD),
                     (malloc._M_TRIM_THRESHOLD, malloc.TRIM_THRESHOLD),
                     (malloc._M_ARENA_MAX, CPU_COUNT)]


@pytest.mark.parametrize("name, value", [
    ("MALLOC_TRIM_THRESHOLD_", "131072"), ("MALLOC_MMAP_THRESHOLD_", "65536"),
    ("MALLOC_TOP_PAD_", "0"), ("MALLOC_ARENA_MAX", "4"), ("GLIBC_TUNABLES", "glibc.malloc.trim_threshold=131072"),
])
def test_a_malloc_tuned_by_the_environment_is_left_alone(fresh, monkeypatch, name, value):
    monkeypatch.setenv(name, value)
    assert not malloc.keep_freed_memory()
    assert fresh == []


def test_a_refused_value_is_reported(fresh, monkeypatch):
    monkeypatch.setattr(malloc, "_glibc_mallopt", lambda: lambda param, value: 0)
    assert not malloc.keep_freed_memory()


def test_another_c_library_changes_nothing(monkeypatch):
    monkeypatch.setattr(platform, "libc_ver", lambda: ("", ""))
    assert malloc._glibc_mallopt() is None


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="glibc only")
def test_glibc_accepts_the_thresholds_and_the_arenas():
    mallopt = malloc._glibc_mallopt()
    assert mallopt is not None
    assert mallopt(malloc._M_MMAP_THRESHOLD, malloc.MMAP_THRESHOLD) == 1
    assert mallopt(malloc._M_TRIM_THRESHOLD, malloc.TRIM_THRESHOLD) == 1
    assert mallopt(malloc._M_ARENA_MAX, CPU_COUNT) == 1


@pytest.mark.parametrize("driver", ["tall", "tree"])
def test_the_drivers_keep_freed_memory(driver, monkeypatch, rng):
    called = []
    module, name = (parallel, "tall_compress") if driver == "tall" else (
        parallel_tree, "tree_compress")
    monkeypatch.setattr(module, "keep_freed_memory", lambda: called.append(True) or True)
    A = rng.standard_normal((40, 12))
    sc = getattr(module, name)(A, block=4, max_rank=3)
    sc.close()
    assert called == [True]


def test_the_command_line_keeps_freed_memory(monkeypatch, rng, tmp_path):
    from streamsvd.cli import main

    called = []
    monkeypatch.setattr(malloc, "keep_freed_memory", lambda: called.append(True) or True)
    np.save(tmp_path / "a.npy", rng.standard_normal((30, 8)))
    assert main(["ingest", str(tmp_path / "a.npy"), str(tmp_path / "s"), "--quiet"]) == 0
    assert called == [True]
