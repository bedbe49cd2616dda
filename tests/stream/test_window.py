"""Removal of absorbed snapshots (Brand's downdate), sliding windows and forgetting.

Every result is checked against LAPACK on the matrix it stands for: the remaining
columns, the last ``window`` snapshots, or the weighted matrix
``[gamma^(m-1) a_1, ..., a_m]``. Tolerances are LAPACK's test ratios
(``||A - U S V^T|| / (||A|| max(n, m) eps) < 50``, ``||I - U^T U|| / (n eps) < 50``).
"""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import streamsvd as ss
from streamsvd.errors import InputError
from streamsvd.parallel.tall import TallCompressor
from streamsvd.testing import assert_svd_contract
from tests._examples import examples

EPS = np.finfo(np.float64).eps


def _data(rng: np.random.Generator, n: int, m: int, rank: int, noise: float) -> np.ndarray:
    """A matrix of rank ``rank`` with singular values 1 to 1e-3, plus noise."""
    L = np.linalg.qr(rng.standard_normal((n, rank)))[0] * np.logspace(0, -3, rank)
    return L @ rng.standard_normal((rank, m)) + noise * rng.standard_normal((n, m))


def _feed(sc: ss.StreamCompressor, A: np.ndarray, sizes: list[int]) -> None:
    start = 0
    for b in sizes:
        if start >= A.shape[1]:
            break
        sc.absorb(A[:, start : start + b])
        start += b
    if start < A.shape[1]:
        sc.absorb(A[:, start:])


def _check_svd(sc: ss.StreamCompressor, B: np.ndarray, *, ratio: float = 50.0) -> None:
    """``sc`` finalised holds the SVD of ``B``: reconstruction, amplitudes, orthogonality."""
    c = sc.copy()
    c.finalize()
    E = c.expansion
    scale = max(B.shape) * EPS * np.linalg.norm(B)
    assert np.linalg.norm(E.to_dense() - B) <= ratio * scale
    s = np.linalg.svd(B, compute_uv=False)
    k = c.rank
    assert k <= s.size
    assert np.max(np.abs(c.amplitudes - s[:k]), initial=0.0) <= ratio * scale
    assert np.linalg.norm(s[k:]) <= ratio * scale  # nothing beyond rounding left out
    assert c.orthogonality_error() <= ratio * B.shape[0] * EPS


# ------------------------------------------------------------------------- remove
@settings(max_examples=examples(25), deadline=None)
@given(
    seed=st.integers(0, 2**16),
    block=st.integers(1, 13),
    removed=st.lists(st.integers(0, 39), min_size=1, max_size=12, unique=True),
    sweeps=st.sampled_from([1, None]),
)
def test_remove_equals_svd_of_remaining_columns(seed, block, removed, sweeps):
    rng = np.random.default_rng(seed)
    A = _data(rng, 50, 40, 12, 1e-6)
    sc = ss.StreamCompressor(50, sweeps=sweeps)
    _feed(sc, A, [block] * 40)
    rec = sc.remove(removed)
    keep = np.setdiff1d(np.arange(40), removed)
    assert rec.kind == "remove" and rec.columns == len(removed)
    assert sc.n_seen == keep.size and sc.n_absorbed == 40
    _check_svd(sc, A[:, keep])
    assert sc.history[-1].kind == "remove"


def test_remove_in_steps_and_then_absorb(rng):
    A = _data(rng, 80, 60, 20, 1e-4)
    sc = ss.StreamCompressor(80, sweeps=None)
    _feed(sc, A[:, :40], [8] * 5)
    sc.remove([3, 5])
    sc.remove(np.array([0, 39, 20]))
    sc.absorb(A[:, 40:])
    sc.remove(45)
    keep = np.setdiff1d(np.arange(60), [0, 3, 5, 20, 39, 45])
    _check_svd(sc, A[:, keep])
    np.testing.assert_array_equal(sc.removed, [[0, 1], [3, 4], [5, 6], [20, 21], [39, 40],
                                               [45, 46]])


def test_remove_with_weights(rng):
    w = rng.uniform(0.5, 2.0, 40)
    A = _data(rng, 40, 30, 10, 1e-5)
    sc = ss.StreamCompressor(40, inner=w, sweeps=None)
    _feed(sc, A, [7] * 5)
    sc.remove(list(range(0, 30, 4)))
    keep = np.setdiff1d(np.arange(30), range(0, 30, 4))
    c = sc.copy()
    c.finalize()
    L = np.sqrt(w)[:, None]
    s = np.linalg.svd(L * A[:, keep], compute_uv=False)
    scale = 40 * EPS * s[0]
    assert np.max(np.abs(c.amplitudes - s[: c.rank])) <= 50 * scale
    assert np.linalg.norm(L * (c.expansion.to_dense() - A[:, keep])) <= 50 * 40 * EPS * s[0]


def test_remove_everything_leaves_an_empty_expansion(rng):
    A = rng.standard_normal((20, 9))
    sc = ss.StreamCompressor(20)
    sc.absorb(A)
    sc.remove(range(9))
    assert sc.n_seen == 0 and sc.rank == 0
    sc.absorb(A[:, :4])
    _check_svd(sc, A[:, :4])


def test_remove_with_truncation_is_the_restriction_and_keeps_the_bound(rng):
    """With a cap the result is the remaining columns of the truncated expansion."""
    A = _data(rng, 120, 100, 30, 1e-3)
    sc = ss.StreamCompressor(120, max_rank=10, oversampling=4, sweeps=None)
    _feed(sc, A, [10] * 10)
    before = sc.expansion.to_dense()
    removed = [0, 7, 33, 34, 35, 80, 99]
    keep = np.setdiff1d(np.arange(100), removed)
    sc.remove(removed)
    B = before[:, keep]
    after = sc.expansion.to_dense()
    assert np.linalg.norm(after - B) <= 50 * 100 * EPS * np.linalg.norm(B)
    rounding = 50 * 120 * EPS * np.linalg.norm(A)
    assert np.linalg.norm(A[:, keep] - after) <= sc.error_bound + rounding
    assert sc.orthogonality_error() <= 50 * 120 * EPS


# ------------------------------------------------------------------------- window
@pytest.mark.parametrize("sizes", [[5] * 20, [1, 7, 30, 2, 11, 3, 40, 6], [25, 1, 1, 50, 23]])
def test_window_equals_svd_of_last_snapshots(rng, sizes):
    A = _data(rng, 60, 100, 15, 1e-5)
    W = 24
    sc = ss.StreamCompressor(60, window=W, sweeps=None)
    start = 0
    for b in sizes:
        sc.absorb(A[:, start : start + b])
        start += b
        assert sc.n_seen == min(W, start) and sc.n_absorbed == start
        _check_svd(sc, A[:, max(0, start - W) : start])


def test_a_direction_only_the_removed_snapshots_carried_leaves_no_term(rng):
    """A zero snapshot in the window: the direction of the snapshot that left is carried
    by none that remain, and its term came out of the downdate at 4e-162 (rank 4 for
    data of rank 3, its right vector not orthogonal to the others: LAPACK ratio 1e15).
    Below reject_tol times the amplitudes before the removal it is cut, its norm counted."""
    n = 7
    a, b, c, d = rng.standard_normal((4, n))
    cols = [a, b, c, np.zeros(n), d]
    sc = ss.StreamCompressor(n, window=4, sweeps=None, rule="jacobi")
    for x in cols:
        sc.absorb(x[:, None])
    rest = np.column_stack(cols[1:])
    assert sc.rank == 3 and any(h.kind == "remove" and h.cut for h in sc.history)
    assert_svd_contract(rest, sc.expansion, error_bound=sc.error_bound)


def test_window_with_truncation_keeps_the_bound_and_stays_flat(rng):
    """A capped window: the bound holds after every update and forgets what left."""
    n, W = 100, 40
    A = _data(rng, n, 400, 8, 1e-3)
    sc = ss.StreamCompressor(n, window=W, max_rank=8, oversampling=4, sweeps=None)
    bounds = []
    for start in range(0, 400, 10):
        sc.absorb(A[:, start : start + 10])
        win = A[:, max(0, start + 10 - W) : start + 10]
        err = np.linalg.norm(win - sc.expansion.to_dense())
        assert err <= sc.error_bound + 50 * n * EPS * np.linalg.norm(win)  # rounding apart
        assert sc.orthogonality_error() <= 50 * n * EPS
        bounds.append(sc.error_bound)
    # the ledger keeps only the discards still on the window: after the first window the
    # bound stays within a constant of a window's noise (the recursion alone would add
    # every discard of the stream)
    noise = 1e-3 * np.sqrt(n * W)
    assert max(bounds[8:]) <= 10 * noise
    assert sum(r.discarded for r in sc.history) > 2 * max(bounds[8:])


def test_window_tall_mode_equals_memory(rng, tmp_path):
    A = _data(rng, 64, 50, 10, 1e-6)
    tc = TallCompressor(64, window=12, chunk_rows=16, sweeps=None)
    _feed(tc, A, [5] * 10)
    tc.remove([44])
    keep = [i for i in range(38, 50) if i != 44]
    _check_svd(tc, A[:, keep])
    tc.close()


# ------------------------------------------------------------------------- forget
@settings(max_examples=examples(25), deadline=None)
@given(
    seed=st.integers(0, 2**16),
    sizes=st.lists(st.integers(1, 9), min_size=1, max_size=12),
    gamma=st.sampled_from([0.5, 0.9, 0.99, 1.0]),
)
def test_forget_equals_svd_of_weighted_matrix(seed, sizes, gamma):
    rng = np.random.default_rng(seed)
    m = 40
    A = _data(rng, 50, m, 12, 1e-6)
    sc = ss.StreamCompressor(50, forget=gamma, sweeps=None)
    _feed(sc, A, sizes)
    Wt = A * gamma ** np.arange(m - 1, -1, -1, dtype=float)
    _check_svd(sc, Wt)


def test_forget_scales_the_bound_and_keeps_it(rng):
    A = _data(rng, 80, 120, 20, 1e-3)
    g = 0.97
    sc = ss.StreamCompressor(80, forget=g, max_rank=8, oversampling=2, sweeps=None)
    for start in range(0, 120, 6):
        sc.absorb(A[:, start : start + 6])
        m = start + 6
        Wt = A[:, :m] * g ** np.arange(m - 1, -1, -1, dtype=float)
        err = np.linalg.norm(Wt - sc.expansion.to_dense())
        assert err <= sc.error_bound + 50 * 80 * EPS * np.linalg.norm(Wt)


def test_forget_without_right_vectors(rng):
    A = _data(rng, 40, 30, 10, 1e-6)
    sc = ss.StreamCompressor(40, forget=0.8, right_vectors=False, sweeps=None)
    _feed(sc, A, [4, 9, 1, 16])
    Wt = A * 0.8 ** np.arange(29, -1, -1, dtype=float)
    s = np.linalg.svd(Wt, compute_uv=False)
    c = sc.copy()
    c.finalize()
    assert np.max(np.abs(c.amplitudes - s[: c.rank])) <= 50 * 40 * EPS * s[0]


# ------------------------------------------------------------------------- the store
def _state(sc: ss.StreamCompressor) -> list[np.ndarray]:
    s = sc._life.state
    return [s.basis.lincomb(s.coords), s.R, sc.right_factor(), np.array([sc.error_bound]),
            sc.removed, np.array(sc._life.ledger.entries)]


@pytest.mark.parametrize("options", [
    {"window": 30, "max_rank": 6, "oversampling": 3},
    {"window": 17, "forget": 0.9},
    {"forget": 0.95, "max_rank": 8},
])
@pytest.mark.parametrize("commit_every", [1, 3])
def test_resume_is_bit_for_bit(rng, tmp_path, options, commit_every):
    sizes = [7, 3, 11, 1, 9] * 8
    A = _data(rng, 70, sum(sizes), 12, 1e-3)

    def run(sc, parts):
        start = sum(sizes[: parts.start])
        for b in sizes[parts]:
            sc.absorb(A[:, start : start + b])
            start += b

    ref = ss.StreamCompressor(70, **options)
    run(ref, slice(0, None))
    ref.remove([ref.n_absorbed - 3])
    sc = ss.StreamCompressor(70, store=tmp_path / "s.zarr", commit_every=commit_every,
                             **options)
    run(sc, slice(0, 17))
    sc.close(finalize=False)  # commits what is pending
    sc = ss.StreamCompressor.open(tmp_path / "s.zarr")
    assert sc.window == options.get("window") and sc.forget == options.get("forget", 1.0)
    run(sc, slice(17, None))
    sc.flush()
    sc.remove([sc.n_absorbed - 3])
    sc.close(finalize=False)
    sc = ss.StreamCompressor.open(tmp_path / "s.zarr", mode="r")
    for a, b in zip(_state(ref), _state(sc), strict=True):
        np.testing.assert_array_equal(a, b)
    assert [r.kind for r in ref.history] == [r.kind for r in sc.history]
    summary = ss.stream.summary_of(sc)
    assert summary["options"]["window"] == options.get("window")
    assert summary["removed"] == sc.removed.tolist()
    sc.close()


def test_dead_rows_are_written_anew_once_they_outnumber_the_live_ones(rng, tmp_path):
    A = _data(rng, 30, 400, 6, 1e-6)
    sc = ss.StreamCompressor(30, window=20, store=tmp_path / "w.zarr", sweeps=None)
    rows = sc._life.state.rows
    rewrites = []
    for start in range(0, 400, 5):
        sc.absorb(A[:, start : start + 5])
        rewrites.append(rows.rewrites)
        assert rows.m - rows.dead.size == sc.n_seen
        assert rows.dead.size <= max(20, 64) + 5
    assert rewrites[-1] >= 3  # the stored rows stay O(window), not O(stream)
    sc.close(finalize=False)
    back = ss.StreamCompressor.open(tmp_path / "w.zarr", mode="r")
    np.testing.assert_array_equal(back.right_factor(), sc.right_factor())
    _check_svd(back, A[:, -20:])
    back.close()


# ------------------------------------------------------------------------- bad input
def test_remove_needs_right_vectors(rng):
    sc = ss.StreamCompressor(10, right_vectors=False)
    sc.absorb(rng.standard_normal((10, 4)))
    with pytest.raises(InputError, match=r"`remove` needs the right vectors.*right_vectors=True"):
        sc.remove([0])


@pytest.mark.parametrize("columns, message", [
    ([5], r"`columns` must be indices of absorbed snapshots, 0 <= index < 5 .*got \[5\]"),
    ([-1], r"0 <= index < 5 .*got \[-1\]"),
    ([1, 2, 1], r"`columns` must name each snapshot once; got \[1\] more than once"),
    ([0], r"`columns` must name snapshots still in the expansion; got \[0\], already removed"),
    ([], r"`columns` must be a non-empty sequence of integer snapshot indices; got \[\]"),
    ([1.5], r"`columns` must be a non-empty sequence of integer snapshot indices; got \[1.5\]"),
])
def test_bad_removals_name_the_argument_and_change_nothing(rng, tmp_path, columns, message):
    sc = ss.StreamCompressor(10, store=tmp_path / "s.zarr")
    sc.absorb(rng.standard_normal((10, 5)))
    sc.remove([0])
    before, generation = _state(sc), sc._life.persistence.handle.generation
    history = sc.history
    with pytest.raises(InputError, match=message):
        sc.remove(columns)
    for a, b in zip(before, _state(sc), strict=True):
        np.testing.assert_array_equal(a, b)
    assert sc._life.persistence.handle.generation == generation and sc.history == history
    sc.close(finalize=False)


@pytest.mark.parametrize("options, message", [
    ({"window": 0}, r"`window` must be an integer >= 1 or None; got int 0"),
    ({"window": 2.5}, r"`window` must be an integer >= 1 or None; got float 2.5"),
    ({"window": 5, "right_vectors": False},
     r"`window` needs the right vectors .*got window=5 with right_vectors=False"),
    ({"forget": 0.0}, r"`forget` must be a number in \(0, 1\] .*got float 0.0"),
    ({"forget": 1.5}, r"`forget` must be a number in \(0, 1\] .*got float 1.5"),
    ({"forget": float("nan")}, r"`forget` must be a number in \(0, 1\] .*got float nan"),
    ({"forget": "x"}, r"`forget` must be a number in \(0, 1\] .*got str 'x'"),
])
def test_bad_window_and_forget_options(options, message):
    with pytest.raises(InputError, match=message):
        ss.StreamCompressor(10, **options)


# ------------------------------------------------------------------------- the command
def _cli(argv, capsys):
    from streamsvd.cli import main

    status = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return status, out, err


@pytest.mark.parametrize("mode", [[], ["--tall"]])
def test_cli_window_and_forget(rng, tmp_path, capsys, mode):
    A = _data(rng, 40, 90, 10, 1e-6)
    np.save(tmp_path / "a.npy", A)
    store = tmp_path / "s.zarr"
    status, out, _ = _cli(["ingest", tmp_path / "a.npy", store, "--window", 25, "--forget",
                           0.9, "--block", 7, *mode], capsys)
    assert status == 0
    summary = json.loads(out)
    assert summary["options"]["window"] == 25 and summary["options"]["forget"] == 0.9
    assert summary["n_seen"] == 25 and summary["n_absorbed"] == 90
    Wt = A[:, -25:] * 0.9 ** np.arange(24, -1, -1, dtype=float)
    s = np.linalg.svd(Wt, compute_uv=False)
    amps = np.array(summary["amplitudes_head"])
    assert np.max(np.abs(amps - s[: amps.size])) <= 50 * 40 * EPS * s[0]
    status, out, _ = _cli(["info", store], capsys)
    assert status == 0 and "window        25 snapshots (forget 0.9); 90 absorbed, 65 removed" in out
    status, _, err = _cli(["ingest", tmp_path / "a.npy", store, "--resume", "--window", 30,
                           *mode], capsys)
    assert status == 2 and "--window 30 (STORE has 25)" in err


@pytest.mark.parametrize("argv, message", [
    (["--window", "0"], "argument --window: must be a positive integer; got '0'"),
    (["--forget", "0"], r"argument --forget: must be a number in \(0, 1\]; got '0'"),
    (["--forget", "1.1"], r"argument --forget: must be a number in \(0, 1\]; got '1.1'"),
    (["--window", "5", "--scheduler", "threads"],
     "--window applies to the in-memory and tall modes only"),
])
def test_cli_bad_window_and_forget(rng, tmp_path, capsys, argv, message):
    np.save(tmp_path / "a.npy", rng.standard_normal((10, 12)))
    status, _, err = _cli(["ingest", tmp_path / "a.npy", tmp_path / "s.zarr", *argv], capsys)
    assert status == 2 and re.search(message, err), err
    assert not (tmp_path / "s.zarr").exists()


# ------------------------------------------------------------------------- estimator
def _pca_reference(X: np.ndarray, w: np.ndarray, k: int):
    mu = (w[:, None] ** 2 * X).sum(0) / float(w @ w)
    return mu, *np.linalg.svd(w[:, None] * (X - mu), full_matrices=False)[1:]


@pytest.mark.parametrize("window, forget, k", [(50, 1.0, 5), (None, 0.97, 4), (40, 0.9, 6)])
def test_estimator_window_and_forget_equal_pca_of_the_weighted_window(rng, window, forget, k):
    from streamsvd.sklearn.estimator import StreamingSVD

    X = rng.standard_normal((300, 12)) @ rng.standard_normal((12, 12)) + 3.0
    est = StreamingSVD(n_components=k, window=window, forget=forget)
    for i in range(0, 300, 17):
        est.partial_fit(X[i : i + 17])
    Xw = X if window is None else X[-window:]
    mw = Xw.shape[0]
    mu, s, Vt = _pca_reference(Xw, forget ** np.arange(mw - 1, -1, -1, dtype=float), k)
    tol = 50 * max(Xw.shape) * EPS * s[0]
    assert est.n_samples_seen_ == mw
    assert np.max(np.abs(est.singular_values_ - s[:k])) <= tol
    assert np.max(np.abs(est.mean_ - mu)) <= tol
    # the components, up to sign, for the well-separated leading ones
    cos = np.abs(np.sum(est.components_ * Vt[:k], axis=1))
    gaps = np.minimum(np.abs(s[:k] - s[1 : k + 1]), np.abs(s[:k] - np.r_[np.inf, s[: k - 1]]))
    assert np.all(1.0 - cos <= (tol / gaps) ** 2 + 50 * EPS)
    C = est.components_ @ est.components_.T
    assert np.linalg.norm(C - np.eye(k), 2) <= 50 * 12 * EPS


@pytest.mark.parametrize("options, message", [
    ({"window": 0}, r"`window` must be an integer >= 1 or None; got int 0"),
    ({"forget": 2.0}, r"`forget` must be a number in \(0, 1\] .*got float 2.0"),
])
def test_estimator_bad_window_and_forget(rng, options, message):
    from streamsvd.sklearn.estimator import StreamingSVD

    with pytest.raises(InputError, match=message):
        StreamingSVD(n_components=2, **options).partial_fit(rng.standard_normal((10, 4)))


def test_estimator_window_may_not_change_between_partial_fits(rng):
    from streamsvd.sklearn.estimator import StreamingSVD

    est = StreamingSVD(n_components=2, window=10)
    est.partial_fit(rng.standard_normal((10, 4)))
    est.window = 20
    with pytest.raises(InputError, match=r"`window` must stay 10 between calls to partial_fit"):
        est.partial_fit(rng.standard_normal((10, 4)))


# ------------------------------------------------------------------------- the bound
@settings(max_examples=examples(20), deadline=None)
@given(
    seed=st.integers(0, 2**16),
    ops=st.lists(st.tuples(st.sampled_from(["absorb", "remove"]), st.integers(1, 8)),
                 min_size=5, max_size=60),
    gamma=st.sampled_from([1.0, 0.95]),
    cap=st.sampled_from([3, 6]),
)
def test_bound_holds_through_any_sequence_of_absorbs_and_removals(seed, ops, gamma, cap):
    """The dense model: the weighted current columns; the bound after every step."""
    rng = np.random.default_rng(seed)
    n = 30
    sc = ss.StreamCompressor(n, forget=gamma, max_rank=cap, oversampling=2,
                             sweeps=int(rng.integers(1, 3)))
    cols: list[np.ndarray] = []  # current columns, weighted
    ids: list[int] = []  # their absorption indices
    for kind, size in ops:
        if kind == "absorb":
            X = _data(rng, n, size, 4, 1e-2)
            sc.absorb(X)
            cols = [c * gamma**size for c in cols]
            cols += [X[:, j] * gamma ** (size - 1 - j) for j in range(size)]
            ids += list(range(sc.n_absorbed - size, sc.n_absorbed))
        elif ids:
            pick = sorted(rng.choice(len(ids), size=min(size, len(ids)), replace=False))
            sc.remove([ids[i] for i in pick])
            cols = [c for i, c in enumerate(cols) if i not in pick]
            ids = [g for i, g in enumerate(ids) if i not in pick]
        assert sc.n_seen == len(cols) and sc._life.ledger.entries.shape[0] <= 32
        A = np.column_stack(cols) if cols else np.zeros((n, 0))
        err = np.linalg.norm(A - sc.expansion.to_dense())
        assert err <= sc.error_bound + 50 * n * EPS * np.linalg.norm(A)
        assert sc.orthogonality_error() <= 50 * n * EPS


def test_a_store_with_removals_has_its_own_layout(rng, tmp_path):
    """Layout 4 until a snapshot is removed, 5 after: a version that reads layout 4 only
    (and knows no dead rows) refuses the store instead of taking dead rows for live ones."""
    from streamsvd.store import open_store
    from streamsvd.stream.persistence import LAYOUT, LAYOUT_WITH_REMOVALS

    A = _data(rng, 40, 30, 8, 1e-3)
    path = tmp_path / "s.zarr"
    with ss.StreamCompressor(40, store=path) as sc:
        sc.absorb(A[:, :20])
        with open_store(path, "r") as st:
            assert st.read().attrs["layout"] == LAYOUT
        sc.remove([3, 4])
        with open_store(path, "r") as st:
            assert st.read().attrs["layout"] == LAYOUT_WITH_REMOVALS
        sc.absorb(A[:, 20:])
    with ss.StreamCompressor.open(path, mode="r") as back:
        assert back.removed.tolist() == [[3, 5]] and back.n_seen == 28
