"""Creating a compressor's store is all or nothing, in every mode; ``check`` agrees with opening.

Every case is deterministic. The write steps of a creation (its directory, its lock,
each object of its root and of its first generation, a panel of the tall mode, the
pointer, the commit record) are found by instrumenting the storage. A process killed
after a step leaves what the store holds at that instant: the test copies the store
there (the copy's lock has no holder, as a dead process's). A failure at a step is an
exception raised there, after which the creation cleans up. Whatever the step, the store
is either absent (or the leftovers of an interrupted creation, which opening refuses and
the next ingest replaces) or complete; ``streamsvd check`` and ``streamsvd info`` say so
alike, and an ingest with ``--resume`` into the same path completes.
"""

from __future__ import annotations

import errno
import shutil
from pathlib import Path

import numpy as np
import pytest

import streamsvd as ss
from streamsvd.algebra.panels.basis import PanelBasis
from streamsvd.algebra.panels.files import PanelFiles
from streamsvd.cli import main
from streamsvd.parallel.cluster import check_store, open_compressor
from streamsvd.parallel.tall import TallCompressor
from streamsvd.storage import LocalStorage, open_storage
from streamsvd.storage.lockfile import FileLock
from streamsvd.store import MARKER_NAME, BasisStore, history, open_store
from streamsvd.stream.compressor import StreamCompressor

N, M, BLOCK, ROWS, RANK = 60, 40, 10, 20, 6
TALL = ("--tall", "--chunk-rows", str(ROWS))

# every call that writes under a store while it is created (the step is the state after
# it), and where it writes
WRITES = (
    (LocalStorage, "prepare", lambda s: s.root),  # the directory
    (FileLock, "acquire", lambda s: s.path.parent),  # the lock file
    # the root documents, the first generation, its commit record
    (LocalStorage, "create", lambda s: s.root),
    (LocalStorage, "put", lambda s: s.root),  # the pointer
    (PanelFiles, "new", lambda s: s.root.root),  # a panel's file, not written yet
    (PanelBasis, "_write", lambda s: s.root.root),  # a panel, written
    (PanelBasis, "_seal", lambda s: s.root.root),  # the checksummed copies a commit lists
)


@pytest.fixture
def source(tmp_path, rng):
    A = rng.standard_normal((N, 8)) @ rng.standard_normal((8, M))
    path = tmp_path / "a.npy"
    np.save(path, A)
    return A, path


def _memory(path, A, tmp):
    StreamCompressor(N, store=path, max_rank=RANK).close(finalize=False)


def _tall(path, A, tmp):
    TallCompressor(N, store=path, chunk_rows=ROWS, max_rank=RANK).close(finalize=False)


def _memory_saved(path, A, tmp):
    sc = StreamCompressor(N, max_rank=RANK)
    sc.absorb(A[:, :BLOCK])
    sc.save(path)
    sc.close(finalize=False)


def _tall_saved(path, A, tmp):
    """The panels of a work directory are copied into the store before its first commit."""
    work = tmp / "work"
    work.mkdir(exist_ok=True)
    tc = TallCompressor(N, workdir=work, chunk_rows=ROWS, max_rank=RANK)
    tc.absorb(A[:, :BLOCK])
    tc.save(path)
    tc.close(finalize=False)


def _cli_memory(path, A, tmp):
    assert main(["ingest", tmp / "a.npy", path, "--block", BLOCK, "--max-rank", RANK,
                 "--quiet"]) == 0


def _cli_tall(path, A, tmp):
    assert main(["ingest", tmp / "a.npy", path, "--block", BLOCK, "--max-rank", RANK,
                 "--quiet", *TALL]) == 0


# how each mode creates its store, its ingest options, and the columns its first commit holds
CREATIONS = {
    "memory": (_memory, (), 0),
    "tall": (_tall, TALL, 0),
    "memory-saved": (_memory_saved, (), BLOCK),
    "tall-saved": (_tall_saved, TALL, BLOCK),
    "cli-memory": (_cli_memory, (), 0),
    "cli-tall": (_cli_tall, TALL, 0),
}


def _instrument(monkeypatch, path, after):
    """Call ``after(label)`` after each write of :data:`WRITES` under ``path``, until the
    first commit record is written (the creation is complete then)."""
    complete = []

    def wrap(cls, name, where):
        real = getattr(cls, name)

        def step(self, *args, **kwargs):
            out = real(self, *args, **kwargs)
            if not complete and Path(where(self)).resolve() == path.resolve():
                key = args[0] if args and isinstance(args[0], str) else ""
                complete.extend([True] if key.endswith(MARKER_NAME) else [])
                after(f"{cls.__name__}.{name}({key})")
            return out
        monkeypatch.setattr(cls, name, step)

    for cls, name, where in WRITES:
        wrap(cls, name, where)


def _assert_opening_and_check_agree(path, first_columns, *, tall):
    """Opening and ``check`` agree: both succeed on a complete store, or both refuse the
    leftovers of an interrupted creation with the same message. Returns whether it opens."""
    if not Path(path).exists():
        return False
    storage = open_storage(path)
    report = check_store(storage)
    try:
        reader = open_compressor(path, mode="r")
    except ss.StoreFormatError as exc:
        assert report.problems == [str(exc)]
        assert history(storage) in ("empty", "creation"), exc  # nothing was committed
        return False
    with reader:
        assert report.healthy, report.problems
        assert history(storage) == "store"
        assert isinstance(reader, TallCompressor) == tall
        assert reader.n_seen == reader.source_offset == first_columns
        if tall:
            assert reader.chunk_rows == ROWS
    return True


def _assert_ingest_completes(path, source_path, options, capsys):
    """``info`` and ``check`` agree; an ingest with --resume into ``path`` completes."""
    capsys.readouterr()
    if Path(path).exists():
        assert (main(["info", path]) == 0) == (main(["check", path]) == 0)
    assert main(["ingest", source_path, path, "--block", BLOCK, "--max-rank", RANK, "--quiet",
                 "--resume", *options]) == 0, capsys.readouterr().err
    assert main(["check", path]) == 0
    with open_compressor(path, mode="r") as done:
        assert done.n_seen == M


@pytest.mark.parametrize("mode", CREATIONS)
def test_a_creation_killed_after_each_write_leaves_nothing_or_a_complete_store(
        tmp_path, monkeypatch, capsys, source, mode):
    A, source_path = source
    create, options, first_columns = CREATIONS[mode]
    path = tmp_path / "s.zarr"
    killed = tmp_path / "killed"
    steps: list[str] = []

    def copy(label):
        steps.append(label)
        if path.exists():
            shutil.copytree(path, killed / f"{len(steps):03d}")

    _instrument(monkeypatch, path, copy)
    create(path, A, tmp_path)
    monkeypatch.undo()
    tall = "tall" in mode
    outcomes = []
    for i in range(1, len(steps) + 1):
        snapshot = killed / f"{i:03d}"
        outcomes.append(_assert_opening_and_check_agree(snapshot, first_columns, tall=tall))
        _assert_ingest_completes(snapshot, source_path, options, capsys)
    # the store exists from its pointer on: refused before, complete from then on
    pointer = next(i for i, label in enumerate(steps) if label.startswith("LocalStorage.put"))
    assert outcomes == [False] * pointer + [True] * (len(steps) - pointer), steps
    if mode == "tall-saved":  # killed with the panels written and no pointer
        assert any(label.startswith("PanelBasis._write") for label in steps[:pointer])


@pytest.mark.parametrize("failure", [OSError(errno.ENOSPC, "No space left on device"),
                                     KeyboardInterrupt()])
@pytest.mark.parametrize("mode", ["memory", "tall", "tall-saved"])
def test_a_creation_failing_at_each_write_leaves_nothing_or_a_complete_store(
        tmp_path, monkeypatch, capsys, source, mode, failure):
    A, source_path = source
    create, options, first_columns = CREATIONS[mode]
    steps: list[str] = []
    probe = tmp_path / "probe.zarr"
    _instrument(monkeypatch, probe, steps.append)
    create(probe, A, tmp_path)
    monkeypatch.undo()
    for i in range(1, len(steps) + 1):
        path = tmp_path / f"s{i:03d}.zarr"
        seen: list[str] = []

        def fail(label, i=i, seen=seen):
            seen.append(label)
            if len(seen) == i:
                raise failure

        _instrument(monkeypatch, path, fail)
        try:
            create(path, A, tmp_path)
        except (OSError, KeyboardInterrupt) as exc:
            assert isinstance(exc, type(failure)) and str(failure) in str(exc), exc
        monkeypatch.undo()
        assert seen[i - 1] == steps[i - 1]
        # a failure before the pointer switch undoes it all; after it, the store stands
        opened = _assert_opening_and_check_agree(path, first_columns, tall="tall" in mode)
        assert opened or not path.exists(), (steps[i - 1], sorted(path.rglob("*")))
        _assert_ingest_completes(path, source_path, options, capsys)


def test_a_store_killed_between_the_two_commits_of_an_earlier_version_is_refused_clearly(
        tmp_path, capsys, source):
    """An earlier version created a store in two commits (the creation's attributes, then
    the state); killed between them, it held no state and no basis attributes, and
    `info` and `--resume` died on ``KeyError: 'chunk_rows'`` while `check` called it
    healthy."""
    A, source_path = source
    path = tmp_path / "old.zarr"
    tc = TallCompressor(N, chunk_rows=ROWS, max_rank=RANK)
    BasisStore.create(path, n=N, inner_fingerprint=tc.inner.fingerprint,
                      attrs=tc._life.attrs(None)).close()
    tc.close(finalize=False)
    with pytest.raises(ss.StoreFormatError, match=r"is an incomplete store: its creation by a "
                       r"TallCompressor was interrupted before its first commit .* Delete it "
                       r"and ingest the snapshots again\.") as refused:
        open_compressor(path)
    assert check_store(open_storage(path)).problems == [str(refused.value)]
    for command in (["info", path], ["check", path],
                    ["ingest", source_path, path, "--resume", "--quiet", *TALL]):
        capsys.readouterr()
        assert main(command) == 2
        out, err = capsys.readouterr()
        assert "incomplete store" in out + err and "Traceback" not in err
    shutil.rmtree(path)  # the advice given
    _assert_ingest_completes(path, source_path, TALL, capsys)


def test_a_commit_without_the_state_of_its_compressor_is_damage_for_open_and_check(tmp_path):
    path = tmp_path / "s.zarr"
    with StreamCompressor(N, store=path, max_rank=RANK):
        pass
    with open_store(path, "a") as st:  # a foreign writer drops the basis's attributes
        state = st.read()
        st.commit(state.arrays, {k: v for k, v in state.attrs.items() if k != "basis"})
    with pytest.raises(ss.StoreFormatError, match=r"is damaged: generation 1 lacks "
                       r"attribute 'basis' of the state a StreamCompressor commits"
                       ) as refused:
        StreamCompressor.open(path)
    assert check_store(open_storage(path)).problems == [str(refused.value)]


def test_check_reports_a_missing_panel_as_opening_does(tmp_path, source):
    A, _ = source
    path = tmp_path / "t.zarr"
    with TallCompressor(N, store=path, chunk_rows=ROWS, max_rank=RANK) as tc:
        tc.absorb(A)
    report = check_store(open_storage(path))
    assert report.healthy and "the TallCompressor it holds opens" in report.verified
    with open_compressor(path) as tc:
        panel = tc._life.state.basis.panels[0]
    shutil.rmtree(path / "panels" / panel)
    with pytest.raises(ss.StoreError, match=rf"panel {panel} of the basis cannot be opened"
                       ) as refused:
        open_compressor(path)
    assert check_store(open_storage(path)).problems == [str(refused.value)]
