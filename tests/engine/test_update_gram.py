"""The absorb through the snapshots' Gram matrix (streamsvd.engine.update_gram): taken when a
target error allows it, as certified as the exact path, never taken where it would lose
digits the target needs."""

import numpy as np
import pytest
import scipy.sparse as sp

import streamsvd as ss
import streamsvd.engine.aside as aside_module
import streamsvd.stream.updates as stream_module
from streamsvd.parallel.cluster import tall_compress
from streamsvd.testing import with_spectrum

EPS = np.finfo(float).eps


def _pulses(n=600, m=360):
    """A travelling, spreading pulse: neighbouring snapshots nearly collinear."""
    x = np.linspace(0.0, 1.0, n)[:, np.newaxis]
    t = np.linspace(0.0, 1.0, m)[np.newaxis, :]
    return np.exp(-((x - 0.2 - 0.6 * t) / (0.05 + 0.05 * t)) ** 2)


def _weights(n):
    return np.linspace(0.5, 1.5, n) / n


def _by_gram(record):
    return record.sweeps == 0 and record.passes in (1, 2)


def _stream(A, block=40, **kw):
    sc = ss.StreamCompressor(A.shape[0], **kw)
    for j in range(0, A.shape[1], block):
        sc.absorb(A[:, j : j + block])
    return sc


def _mean_l2(A, U, V, w):
    R = A - U @ V.T
    return np.sqrt(np.sum(w[:, np.newaxis] * R * R) / A.shape[1])


@pytest.fixture
def exact_only(monkeypatch):
    """Force the exact path (for comparisons)."""
    monkeypatch.setattr(stream_module, "plan_absorb_by_gram", lambda *a, **k: None)


@pytest.mark.parametrize("target", [1e-2, 1e-3, 1e-4])
def test_nearly_collinear_snapshots_take_the_gram_path_with_a_bound_that_holds(target):
    A = _pulses()
    w = _weights(A.shape[0])
    kw = dict(inner=w, target_error=target, error_measure="mean_l2")
    sc = ss.StreamCompressor(A.shape[0], **kw)
    for j in range(0, A.shape[1], 40):
        rec = sc.absorb(A[:, j : j + 40])
        assert _by_gram(rec)
        E = sc.expansion
        err = _mean_l2(A[:, : j + 40], E.U, E.V, w)
        assert err <= sc.error_in_measure * (1 + 1e-9)
        U = E.U
        assert np.linalg.norm(U.T @ (w[:, np.newaxis] * U) - np.eye(U.shape[1]), 2) <= (
            50 * A.shape[0] * EPS)
    sc.finalize()
    E = sc.expansion
    err = _mean_l2(A, E.U, E.V, w)
    assert err <= sc.error_in_measure <= target
    assert sc.error_in_measure <= 1.5 * err
    # the optimum: the fewest modes of the weighted SVD within the target
    s = np.linalg.svd(np.sqrt(w)[:, np.newaxis] * A, compute_uv=False)
    tail = np.sqrt(np.append(np.cumsum((s * s)[::-1])[::-1], 0.0) / A.shape[1])
    assert sc.rank <= int(np.flatnonzero(tail <= target)[0]) + 1
    Vh = E.V / np.linalg.norm(E.V, axis=0)
    assert np.linalg.norm(Vh.T @ Vh - np.eye(sc.rank), 2) <= 50 * A.shape[1] * EPS


def test_the_gram_path_keeps_the_exact_paths_modes_and_bound(monkeypatch):
    A = _pulses()
    kw = dict(target_error=1e-3, error_measure="mean_l2")
    fast = _stream(A, **kw)
    assert all(_by_gram(r) for r in fast.history)
    fast.finalize()
    monkeypatch.setattr(stream_module, "plan_absorb_by_gram", lambda *a, **k: None)
    # the exact path as the Gram path's reference: nothing set aside before the cut
    # (what setting aside changes is tested in tests/linalg/test_extend.py)
    monkeypatch.setattr(aside_module, "_ASIDE_SHARE", 0.0)
    exact = _stream(A, **kw)
    assert not any(_by_gram(r) for r in exact.history)
    exact.finalize()
    assert abs(fast.rank - exact.rank) <= 1
    assert fast.error_bound == pytest.approx(exact.error_bound, rel=0.05)
    np.testing.assert_allclose(fast.amplitudes[:10], exact.amplitudes[:10], rtol=1e-9)


@pytest.mark.parametrize("kw, block", [
    ({"target_error": 1e-9, "error_measure": "relative"}, 40),  # below the Gram's rounding
    ({}, 40),  # nothing is cut: every digit is the user's
    ({"rtol": 1e-3}, 40),  # a threshold after the rule's sweeps (Algorithm 3)
])
def test_the_exact_path_runs_where_the_gram_would_lose_needed_digits_or_time(kw, block):
    A = _pulses()
    sc = _stream(A, block=block, **kw)
    assert not any(_by_gram(r) for r in sc.history)


@pytest.mark.parametrize("kw", [
    {"max_rank": 12},
    {"target_error": 1e-2, "error_measure": "absolute"},
])
def test_a_cut_by_rank_threshold_or_absolute_target_takes_the_gram_path(
    kw, monkeypatch, rng
):
    """On a spectrum decaying to 1e-5, what the rounding of the Gram can lose is below
    1% of what each cut drops: the Gram path runs and keeps the exact path's modes,
    amplitudes and bound."""
    A = with_spectrum(np.logspace(0, -5, 200), 600, 360, rng)
    fast = _stream(A, **kw)
    assert any(_by_gram(r) for r in fast.history)
    fast.finalize()
    E = fast.expansion
    assert np.linalg.norm(A - E.U @ E.V.T) <= fast.error_bound * (1 + 1e-9)
    monkeypatch.setattr(stream_module, "plan_absorb_by_gram", lambda *a, **k: None)
    exact = _stream(A, **kw)
    exact.finalize()
    assert abs(fast.rank - exact.rank) <= 1
    assert fast.error_bound <= 1.01 * exact.error_bound
    k = min(fast.rank, exact.rank)
    np.testing.assert_allclose(fast.amplitudes[:k], exact.amplitudes[:k], rtol=1e-6)


def _count_products(monkeypatch):
    """Count the block products of the Gram path (a list, one entry per product)."""
    import streamsvd.engine.update_gram as update_gram

    made = []
    products = update_gram._products

    def counted(*args, **kwargs):
        made.append(1)
        return products(*args, **kwargs)

    monkeypatch.setattr(update_gram, "_products", counted)
    return made


@pytest.mark.parametrize("measure, target", [("absolute", 1e-5), ("relative", 1e-9)])
def test_a_target_the_rounding_cannot_meet_skips_the_blocks_products(measure, target,
                                                                      monkeypatch):
    """Below what the Gram's rounding can certify the update is refused before the
    block's M product and Gram (what the energy absorbed before, or a unit of it,
    already allows), with the digits of the exact path alone."""
    made = _count_products(monkeypatch)
    A = _pulses()
    kw = {"target_error": target, "error_measure": measure}
    fast = _stream(A, **kw)
    assert not any(_by_gram(r) for r in fast.history)
    assert len(made) <= 1  # the first block only: nothing absorbed before it
    monkeypatch.setattr(stream_module, "plan_absorb_by_gram", lambda *a, **k: None)
    exact = _stream(A, **kw)
    np.testing.assert_array_equal(fast.amplitudes, exact.amplitudes)
    assert fast.error_bound == exact.error_bound


@pytest.mark.parametrize("zero_first", [False, True])
@pytest.mark.parametrize("scale", [2.0**-664, 2.0**664])
def test_the_gram_path_on_extreme_scales(scale, zero_first):
    """Data scaled by 2^-664 or 2^664 (about 1e-200 and 1e200): the same decisions and
    a bound scaled exactly (powers of two scale without rounding). With a zero first
    column in each block (a trajectory starting at rest) too: the block's energy was once
    ``0 * inf``, a NaN that let the rounding allowance pass unchecked."""
    A = _pulses()
    if zero_first:
        A[:, ::40] = 0.0
    kw = dict(target_error=1e-4, error_measure="relative")
    ref = _stream(A, **kw)
    sc = _stream(scale * A, **kw)
    assert all(_by_gram(r) for r in sc.history)
    assert sc.rank == ref.rank
    assert sc.error_bound == pytest.approx(scale * ref.error_bound, rel=1e-12, abs=0)
    E = sc.expansion
    err = np.linalg.norm(A - E.U @ (E.V / scale).T)  # scaled back: no overflow here
    assert err <= (sc.error_bound / scale) * (1 + 1e-9)


def test_the_tall_mode_takes_the_same_gram_path(rng):
    A = _pulses()
    kw = dict(target_error=1e-3, error_measure="relative")
    mem = _stream(A, **kw)
    tall = tall_compress(A, block=40, chunk_rows=256, **kw)
    assert all(_by_gram(r) for r in tall.history)
    assert tall.rank == mem.rank
    U, V = tall.factors()
    E = mem.expansion
    # the chunked products round differently; the difference is far below the bound
    diff = np.linalg.norm(np.asarray(U) @ V.T - E.U @ E.V.T)
    assert diff <= 1e-6 * mem.error_bound
    tall.close()


def test_an_interrupted_gram_absorb_changes_nothing(tmp_path, monkeypatch):
    A = _pulses()
    path = tmp_path / "s.zarr"
    kw = dict(target_error=1e-3, error_measure="mean_l2")
    with ss.StreamCompressor(A.shape[0], store=path, **kw) as sc:
        for j in range(0, 200, 40):
            sc.absorb(A[:, j : j + 40])
        sc.flush()
        before = sc.expansion
        basis = sc._life.state.basis

        def interrupt(*args, **kwargs):
            raise KeyboardInterrupt

        with monkeypatch.context() as mp:
            mp.setattr(basis, "compact_with_block", interrupt)
            with pytest.raises(KeyboardInterrupt):
                sc.absorb(A[:, 200:240])
        after = sc.expansion
        np.testing.assert_array_equal(after.U, before.U)
        np.testing.assert_array_equal(after.V, before.V)
        assert sc.n_seen == 200
        sc.absorb(A[:, 200:240])
        assert sc.n_seen == 240
        sc.close(finalize=False)
    with ss.StreamCompressor.open(path) as back:
        assert back.n_seen == 240


@pytest.mark.parametrize("inner", [None, "weights"])
def test_a_merge_that_cuts_takes_the_gram_path_and_keeps_the_exact_paths_result(
        rng, monkeypatch, inner):
    """Two halves of a stream merged under a rank cap: two passes and no sweep, the
    other's left vectors never formed; the same amplitudes and right vectors as the
    exact merge to a few eps of the largest over the smallest kept, orthonormal factors
    measured from themselves, and a bound that holds (with the right vectors kept, in a
    weighted inner product too)."""
    n, m = 2000, 240
    A = with_spectrum(np.logspace(0, -6, 60), n, m, rng)
    w = _weights(n) if inner else None
    kw = dict(max_rank=20, right_vectors=True, inner=w)

    def merged():
        left = _stream(A[:, :m // 2], **kw)
        right = _stream(A[:, m // 2:], **kw)
        left.merge(right, spend_target=False)
        return left

    monkeypatch.setattr(ss.basis.MemoryBasis, "lincomb", lambda *a: pytest.fail("U_o formed"))
    fast = merged()
    monkeypatch.undo()
    assert _by_gram(fast.history[-1]) and fast.history[-1].kind == "merge"
    monkeypatch.setattr(stream_module, "plan_merge_by_gram", lambda *a, **k: None)
    exact = merged()
    assert not _by_gram(exact.history[-1])
    for sc in (fast, exact):
        sc.finalize()
    k = fast.rank
    assert k == exact.rank == 20
    s = fast.amplitudes
    tol = 100 * np.sqrt(n) * EPS * s[0] ** 2 / s[k - 1]
    np.testing.assert_allclose(fast.amplitudes, exact.amplitudes, rtol=0, atol=tol)
    U, V = fast.expansion.U, fast.expansion.V
    M = np.ones(n) if w is None else w
    assert np.linalg.norm(U.T @ (M[:, np.newaxis] * U) - np.eye(k), 2) <= 50 * n * EPS
    Y = V / s
    assert np.linalg.norm(Y.T @ Y - np.eye(k), 2) <= 50 * m * EPS
    R = A - U @ V.T
    assert np.sqrt(np.sum(M[:, np.newaxis] * R * R)) <= fast.error_bound * (1 + 1e-12)


def test_merging_an_expansion_takes_the_same_gram_path(rng):
    """An Expansion (its U formed, no basis of its own) merges through the Gram path as
    the compressor it came from does."""
    n, m = 1500, 160
    A = with_spectrum(np.logspace(0, -6, 50), n, m, rng)
    left = _stream(A[:, :80], max_rank=15)
    right = _stream(A[:, 80:], max_rank=15)
    via_expansion = left.copy()
    via_expansion.merge(right.expansion, spend_target=False)
    left.merge(right, spend_target=False)
    for sc in (left, via_expansion):
        assert _by_gram(sc.history[-1])
        sc.finalize()
    s = left.amplitudes
    np.testing.assert_allclose(via_expansion.amplitudes, s, rtol=0,
                               atol=100 * np.sqrt(n) * EPS * s[0] ** 2 / s[-1])


def test_a_merge_of_scales_far_apart_takes_the_exact_path(rng):
    """Amplitudes 1e250 and 1e-250 have no common power-of-two scaling (the other's
    energy would underflow in the Gram): the merge is left to the exact path, and every
    term and the bound stay finite."""
    n = 300
    A = with_spectrum(np.logspace(0, -3, 20), n, 40, rng)
    big, small = _stream(A[:, :20] * 1e250, max_rank=8), _stream(A[:, 20:] * 1e-250, max_rank=8)
    big.merge(small, spend_target=False)
    assert not _by_gram(big.history[-1])
    assert np.all(np.isfinite(big.amplitudes)) and np.isfinite(big.error_bound)
    dense = big.expansion.to_dense()
    R = (A[:, :20] * 1e250 - dense[:, :20]) * 1e-250  # scaled: the squares would overflow
    assert np.linalg.norm(R) <= big.error_bound * 1e-250 * (1 + 1e-12)


# ------------------------------------------------------------ compacting in place


def _in_place(n, **kw):
    from streamsvd.algebra.memory import MemoryBackend

    return ss.StreamCompressor(n, backend=MemoryBackend(compact_in_place=True), **kw)


@pytest.mark.slow
@pytest.mark.parametrize("inner", [None, "weights"])
def test_a_basis_compacting_in_place_keeps_the_expansion_with_one_buffer_less(inner, rng):
    """Written over the stored columns slab by slab, the Gram path's compaction gives the
    expansion written aside (the same products, row by row), and the basis keeps no
    compaction buffer: its traced peak is about one ``n x k`` buffer lower."""
    import tracemalloc

    from streamsvd._util.slabs import SLAB_BYTES

    n = 60000
    A = with_spectrum(np.logspace(0, -10, 120), n, 240, rng)
    kw = dict(max_rank=30, inner=None if inner is None else _weights(n))
    peaks, results = [], []
    for make in (lambda: ss.StreamCompressor(n, **kw), lambda: _in_place(n, **kw)):
        tracemalloc.start()
        sc = make()
        sc.absorb(A[:, :40])
        tracemalloc.reset_peak()  # the updates that compact through the Gram
        for j in range(40, 240, 40):
            assert _by_gram(sc.absorb(A[:, j:j + 40]))
        peaks.append(tracemalloc.get_traced_memory()[1])
        tracemalloc.stop()
        results.append(sc)
    aside, over = results
    assert over._life.state.basis._spare is None and aside._life.state.basis._spare is not None
    k = over._life.state.basis.capacity
    images = 1 if inner is None else 2  # the basis, and its M image
    # a slab of rows per part, and the last, shorter ones
    assert peaks[1] <= peaks[0] - images * n * k * 8 + 4 * SLAB_BYTES
    Ea, Eo = aside.expansion, over.expansion
    s1 = Ea.amplitudes[0]
    np.testing.assert_allclose(Eo.amplitudes, Ea.amplitudes, rtol=0,
                               atol=100 * np.sqrt(n) * EPS * s1)
    # the difference of the products in the norm the amplitudes are measured in (M)
    root_w = np.ones(n) if inner is None else np.sqrt(_weights(n))
    gap = np.linalg.norm(root_w[:, np.newaxis] * (Eo.U @ Eo.V.T - Ea.U @ Ea.V.T))
    assert gap <= 100 * np.sqrt(n) * EPS * s1
    assert over.error_bound == pytest.approx(aside.error_bound, rel=1e-9, abs=0)
    # orthonormality measured from the factors
    U = Eo.U
    MU = U if inner is None else _weights(n)[:, np.newaxis] * U
    assert np.linalg.norm(U.T @ MU - np.eye(U.shape[1]), 2) <= 50 * n * EPS


def test_an_interrupted_in_place_compaction_breaks_the_compressor_and_says_so(rng):
    import streamsvd.engine.update_gram as update_gram

    n = 3000
    A = with_spectrum(np.logspace(0, -10, 80), n, 200, rng)
    sc = _in_place(n, max_rank=20)
    for j in range(0, 100, 50):
        sc.absorb(A[:, j:j + 50])

    def interrupt(*args, **kwargs):
        raise KeyboardInterrupt

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(update_gram, "dtrtri", interrupt)  # after the compaction
        with pytest.raises(KeyboardInterrupt):
            sc.absorb(A[:, 100:150])
    with pytest.raises(ss.BrokenStateError, match="compact_in_place=True"):
        sc.absorb(A[:, 100:150])
    with pytest.raises(ss.BrokenStateError):
        _ = sc.expansion


def test_a_tree_whose_in_place_updates_break_compresses_them_again_aside(
        rng, monkeypatch, caplog):
    """Should the Gram path decline a basis it wrote over the stored one (its rounding
    bound rules that out), the leaf or merge is made again compacting aside: the tree
    completes with a bound that holds, and the user's root compacts aside."""
    import logging

    import streamsvd.engine.update_gram as update_gram
    from streamsvd.parallel.cluster import tree_compress

    n, m = 2000, 400
    A = with_spectrum(np.logspace(0, -10, 100), n, m, rng)
    monkeypatch.setattr(update_gram, "_MAX_DRIFT", -1.0)  # every Gram compaction declined
    with caplog.at_level(logging.WARNING, logger="streamsvd.parallel.tree"):
        sc = tree_compress(A, block=50, leaf_columns=100, max_rank=20)
    assert "compressed again, compacting aside" in caplog.text  # a leaf
    assert "made again, compacting aside" in caplog.text  # a merge
    assert not sc._life.state.basis.compact_in_place
    E = sc.expansion
    assert np.linalg.norm(A - E.U @ E.V.T) <= sc.error_bound * (1 + 1e-12)
    monkeypatch.undo()
    reference = tree_compress(A, block=50, leaf_columns=100, max_rank=20)
    s = E.amplitudes
    np.testing.assert_allclose(s, reference.expansion.amplitudes, rtol=0,
                               atol=1e3 * np.sqrt(n) * EPS * s[0])


# ------------------------------------------------------- the Gram measured one update later
def _pending_stream(rng, inner=None, n=300, m=160, block=20):
    A = with_spectrum(np.logspace(0, -8, 60), n, m, rng)
    sc = ss.StreamCompressor(n, inner=inner, max_rank=12)
    return A, sc, [A[:, j : j + block] for j in range(0, m, block)]


def _m_gram(U, inner):
    MU = U if inner is None else (inner[:, np.newaxis] * U if np.ndim(inner) == 1 else inner @ U)
    return U.T @ MU


@pytest.mark.parametrize("block", [6, 20])
@pytest.mark.parametrize("inner", [None, "weights"])
def test_the_gram_path_leaves_the_new_bases_gram_to_the_next_block(rng, inner, block):
    """After an update by the Gram path the in-memory basis's Gram is pending; the next
    one measures it (in one product with its block, the Gram of [Q, X], when the block
    is at most half the basis's width: 6 of 22 columns, not 20); read before, the
    factors are orthonormal to working accuracy, measured from U itself."""
    n = 300
    ip = None if inner is None else np.linspace(0.5, 2.0, n)
    A, sc, blocks = _pending_stream(rng, ip, n, block=block)
    joint = []
    sc._life.state.basis.joint_products = _counted(sc._life.state.basis.joint_products, joint)
    for X in blocks:
        rec = sc.absorb(X)
        state = sc._life.state
        if sc.n_seen <= 22:
            continue  # nothing cut yet: the exact path
        assert _by_gram(rec) and state.gram is None
        # its Gram is measured and the small factors carry its loss of orthogonality
        coords, H, R = state.settled()
        assert state.gram is None  # reading it changed nothing
        U = state.basis.Q @ coords
        G = _m_gram(U, ip)
        assert np.linalg.norm(G - np.eye(G.shape[0]), 2) <= 20 * n * EPS
        # the recorded orthogonality is the one the Gram of [Q, X] predicted: about
        # eps lambda_1 / lambda_k, the loss of orthogonality that the Gram then removes
        amps = np.abs(np.diag(state.R))
        size = state.rank + X.shape[1]
        assert 0.0 <= rec.orthogonality <= size * EPS * (amps.max() / amps.min()) ** 2
        # the expansion is unchanged by the measurement: Q R^T Y^T either way
        np.testing.assert_allclose(state.basis.Q @ state.R.T, U @ R.T, rtol=0,
                                   atol=1e3 * EPS * np.abs(state.R).max())
    E = sc.expansion
    assert E.orthogonality_error() <= 20 * n * EPS
    # every update after one by the Gram path measures its Gram with the block, when
    # the block is narrow
    assert len(joint) == (sum(_by_gram(r) for r in sc.history[:-1]) if block == 6 else 0)


def _counted(method, calls):
    def counted(*args, **kwargs):
        calls.append(1)
        return method(*args, **kwargs)
    return counted


def _bases_and_blocks(rng, n, w, b):
    """Yield ``(basis, inner, X)``: an orthonormal in-memory basis of ``w`` columns and a
    Gaussian block of ``b``, for the Euclidean and a weighted inner product."""
    from streamsvd.algebra.inner import as_inner
    from streamsvd.algebra.memory import MemoryBasis

    for weights in (None, np.linspace(0.5, 2.0, n)):
        inner = as_inner(weights, n)
        basis = MemoryBasis(n, inner, capacity=4)
        Y, MY = basis.workspace(w)
        Y[...] = np.linalg.qr(rng.standard_normal((n, w)))[0]
        MY[...] = inner.apply(Y) if weights is not None else Y
        basis.accept(w)
        yield basis, inner, np.asfortranarray(rng.standard_normal((n, b)))


def test_the_joint_product_gives_the_separate_ones(rng):
    """MemoryBasis.joint_products: the block's Gram, its projection and the basis's Gram
    in one product, each within rounding of the separate products."""
    n, w, b = 500, 12, 7
    for basis, inner, X in _bases_and_blocks(rng, n, w, b):
        S, C, H = basis.joint_products(X)
        MQ, MX = basis.MQ, inner.apply(X)
        Q = basis.Q
        tol = 10 * n * EPS * max(1.0, np.abs(X).max() ** 2)
        np.testing.assert_allclose(S, X.T @ MX, rtol=0, atol=tol)
        np.testing.assert_allclose(C, MQ.T @ X, rtol=0, atol=tol)
        np.testing.assert_allclose(H, Q.T @ MQ, rtol=0, atol=tol)
        np.testing.assert_array_equal(S, S.T)
        assert basis.width == w  # the block is staged, not stored


@pytest.mark.parametrize("block", [2, 6, 20])
def test_reading_between_updates_changes_no_digit(rng, block):
    """A compressor read between two updates (left vectors, amplitudes, orthogonality,
    a copy) continues exactly as one that is not: reading measures the pending Gram
    aside, the next update measures it with its block or alone."""
    A, quiet, blocks = _pending_stream(rng, block=block)
    _, read, _ = _pending_stream(rng, block=block)
    for X in blocks:
        quiet.absorb(X)
        read.absorb(X)
        read.expansion, read.amplitudes, read.orthogonality_error(), read.copy()
    for a, b in ((quiet.expansion.U, read.expansion.U), (quiet.expansion.V, read.expansion.V)):
        np.testing.assert_array_equal(a, b)
    assert quiet.history[-1].orthogonality == read.history[-1].orthogonality


@pytest.mark.parametrize("block", [6, 20])
def test_a_pending_gram_is_committed_so_and_resumed_bit_for_bit(tmp_path, rng, block):
    """A commit of a pending state writes layout 6 (the small state's Gram not stored),
    which a version reading 4 and 5 only refuses; reopened, the stream continues as the
    uninterrupted one, digit for digit."""
    from streamsvd.store import open_store
    from streamsvd.stream.persistence import LAYOUT, PENDING_GRAM

    A, ref, blocks = _pending_stream(rng, block=block)
    for X in blocks:
        ref.absorb(X)
    path = tmp_path / "s.zarr"
    half = len(blocks) // 2
    with ss.StreamCompressor(A.shape[0], store=path, max_rank=12) as sc:
        for X in blocks[:half]:
            sc.absorb(X)
        assert sc._life.state.gram is None
        sc.close(finalize=False)
    st = open_store(path, "r")
    try:
        assert st.read().attrs["layout"] == LAYOUT + PENDING_GRAM
    finally:
        st.close()
    with ss.StreamCompressor.open(path) as back:
        assert back._life.state.gram is None
        assert back.expansion.orthogonality_error() <= 20 * A.shape[0] * EPS
        for X in blocks[half:]:
            back.absorb(X)
        np.testing.assert_array_equal(back.expansion.U, ref.expansion.U)
        np.testing.assert_array_equal(back.expansion.V, ref.expansion.V)
        back.finalize()
        assert back._life.state.gram is not None  # the final sweeps measured it


def test_a_pending_basis_that_lost_its_orthogonality_is_refused_by_name(rng):
    """Should the basis whose Gram is pending turn out singular when measured (its
    rounding beyond what the update checked: never observed; here a column zeroed by
    hand), reading it raises BrokenStateError, and the state is left as it was."""
    A, sc, blocks = _pending_stream(rng)
    for X in blocks:
        sc.absorb(X)
    state = sc._life.state
    assert state.gram is None
    state.basis.Q[:, 3] = 0.0
    R = state.R.copy()
    with pytest.raises(ss.BrokenStateError, match="lost its orthogonality"):
        sc.orthogonality_error()
    assert state.gram is None and np.array_equal(state.R, R)


def test_a_block_wider_than_half_the_basis_is_not_copied_beside_it(rng):
    """Copying the block beside a pending basis holds both of the basis's buffers b
    columns wider (at n = 200000 and b = 100: 320 MB): blocks wider than half the basis
    have their Gram measured alone, and the buffers stay as wide as the basis."""
    for block, widened in ((20, False), (6, True)):
        A, sc, blocks = _pending_stream(rng, block=block)
        for X in blocks:
            sc.absorb(X)
        basis = sc._life.state.basis
        assert sc.history[-1].passes == 2 and basis.width == 22
        assert (basis.capacity >= basis.width + block) == widened


def _kept(record):
    """An update by the Gram path that kept its block beside the basis (no compaction)."""
    return record.sweeps == 0 and record.passes == 1


def _m_norm(R, inner):
    return np.sqrt(np.sum(R * R) if inner is None else np.sum(inner[:, np.newaxis] * R * R))


@pytest.mark.parametrize("inner", [None, "weights"])
def test_narrow_blocks_stay_beside_the_basis_and_keep_the_exact_paths_result(
        inner, monkeypatch, rng):
    """A block at most a quarter as wide as the terms is kept beside the basis (one
    product per update, no compaction) while the stored width stays within twice the
    terms; U = Q coords stays orthonormal to working accuracy, measured from U itself,
    and the modes, amplitudes and bound are the exact path's."""
    n, m, block, cap = 600, 360, 5, 20
    ip = None if inner is None else np.linspace(0.5, 2.0, n)
    A = with_spectrum(np.logspace(0, -5, 200), n, m, rng)
    sc = ss.StreamCompressor(n, inner=ip, max_rank=cap)
    width = 0
    for j in range(0, m, block):
        rec = sc.absorb(A[:, j : j + block])
        basis = sc._life.state.basis
        if _kept(rec):
            assert basis.width == width + block  # stored as it is
        width = basis.width
        assert width <= 2 * sc.rank
        U = sc.expansion.U
        assert np.linalg.norm(_m_gram(U, ip) - np.eye(U.shape[1]), 2) <= 20 * n * EPS
        assert rec.orthogonality <= 20 * n * EPS
    kept = sum(_kept(r) for r in sc.history)
    assert kept >= len(sc.history) // 2
    sc.finalize()
    E = sc.expansion
    assert _m_norm(A - E.U @ E.V.T, ip) <= sc.error_bound * (1 + 1e-9)
    monkeypatch.setattr(stream_module, "plan_absorb_by_gram", lambda *a, **k: None)
    exact = _stream(A, block=block, inner=ip, max_rank=cap)
    exact.finalize()
    assert sc.rank == exact.rank
    assert sc.error_bound <= 1.01 * exact.error_bound
    np.testing.assert_allclose(sc.amplitudes, exact.amplitudes, rtol=1e-6)


@pytest.mark.parametrize("target, kept", [(1e-2, True), (1e-4, False)])
def test_nearly_collinear_narrow_blocks_are_kept_only_where_u_keeps_its_digits(target, kept):
    """Time steps two at a time: the blocks are nearly collinear with the basis. At 1e-2
    some are kept beside it, and U = [Q, Y] coords, whose columns cancel, is formed to
    working accuracy; at 1e-4 the kept terms span eigenvalues of the Gram too far apart
    for that (U would lose about eps lambda_1 / lambda_k), and every block is compacted.
    The bound and the orthogonality hold at every update either way."""
    A = _pulses()
    w = _weights(A.shape[0])
    sc = ss.StreamCompressor(A.shape[0], inner=w, target_error=target,
                             error_measure="mean_l2")
    for j in range(0, A.shape[1], 2):
        sc.absorb(A[:, j : j + 2])
        E = sc.expansion
        assert _mean_l2(A[:, : j + 2], E.U, E.V, w) <= sc.error_in_measure * (1 + 1e-9)
        assert np.linalg.norm(_m_gram(E.U, w) - np.eye(sc.rank), 2) <= 20 * A.shape[0] * EPS
    assert any(_kept(r) for r in sc.history) == kept
    sc.finalize()
    assert sc.error_in_measure <= target


@pytest.mark.slow
def test_kept_blocks_are_committed_and_resumed_bit_for_bit(tmp_path, rng):
    """A commit while the basis holds kept blocks stores them as columns of the basis;
    reopened, the stream continues as the uninterrupted one, digit for digit."""
    n, block = 400, 4
    A = with_spectrum(np.logspace(0, -6, 100), n, 200, rng)
    blocks = [A[:, j : j + block] for j in range(0, A.shape[1], block)]
    ref = ss.StreamCompressor(n, max_rank=16)
    holding = []
    for i, X in enumerate(blocks):
        ref.absorb(X)
        if ref._life.state.basis.width > ref.rank:
            holding.append(i)
    half = holding[len(holding) // 2] + 1
    path = tmp_path / "s.zarr"
    with ss.StreamCompressor(n, store=path, max_rank=16) as sc:
        for X in blocks[:half]:
            sc.absorb(X)
        assert sc._life.state.basis.width > sc.rank
        sc.close(finalize=False)
    with ss.StreamCompressor.open(path) as back:
        assert back._life.state.basis.width > back.rank
        for X in blocks[half:]:
            back.absorb(X)
        np.testing.assert_array_equal(back.expansion.U, ref.expansion.U)
        np.testing.assert_array_equal(back.expansion.V, ref.expansion.V)


def test_an_interrupted_update_that_keeps_its_block_changes_nothing(tmp_path, monkeypatch,
                                                                    rng):
    """Interrupted after its block was copied beside the basis, an update leaves the
    stored width, the expansion and the store as they were; the next absorb of the same
    block keeps it."""
    import streamsvd.engine.gram_path as gram_path

    n = 400
    A = with_spectrum(np.logspace(0, -6, 100), n, 120, rng)
    path = tmp_path / "s.zarr"
    with ss.StreamCompressor(n, store=path, max_rank=16) as sc:
        j = 0
        while not (sc.history and _kept(sc.history[-1])):
            sc.absorb(A[:, j : j + 2])
            j += 2
        sc.flush()
        before, width = sc.expansion, sc._life.state.basis.width

        def interrupt(*args, **kwargs):
            raise KeyboardInterrupt

        with monkeypatch.context() as mp:
            mp.setattr(gram_path, "dtrtri", interrupt)  # in _kept_factors
            with pytest.raises(KeyboardInterrupt):
                sc.absorb(A[:, j : j + 2])
        assert sc._life.state.basis.width == width and sc.n_seen == j
        np.testing.assert_array_equal(sc.expansion.U, before.U)
        np.testing.assert_array_equal(sc.expansion.V, before.V)
        assert _kept(sc.absorb(A[:, j : j + 2]))
        sc.close(finalize=False)
    with ss.StreamCompressor.open(path) as back:
        assert back.n_seen == j + 2


def test_the_products_beside_the_basis_give_the_separate_ones_and_keep_the_block(rng):
    """MemoryBasis.products_beside: the block's Gram and its projection in one product,
    each within rounding of the separate products; the block is staged after the stored
    columns, and accepting it makes it stored columns as they are."""
    n, w, b = 500, 12, 3
    for basis, inner, X in _bases_and_blocks(rng, n, w, b):
        S, C = basis.products_beside(X)
        MX = inner.apply(X)
        tol = 10 * n * EPS * max(1.0, np.abs(X).max() ** 2)
        np.testing.assert_allclose(S, X.T @ MX, rtol=0, atol=tol)
        np.testing.assert_allclose(C, basis.MQ.T @ X, rtol=0, atol=tol)
        np.testing.assert_array_equal(S, S.T)
        assert basis.width == w and basis.block_beside
        basis.accept(b)
        assert basis.width == w + b and not basis.block_beside
        np.testing.assert_array_equal(basis.Q[:, w:], X)
        np.testing.assert_array_equal(basis.MQ[:, w:], MX)


def test_the_residual_products_give_the_separate_ones(rng):
    """MemoryBasis.residual_products: what a residual in the workspace keeps along the
    basis and its Gram (one product over [MQ, MZ] with a matrix M), each within rounding
    of the separate products; a residual elsewhere gets the separate products."""
    n, w, b = 500, 12, 7
    for basis, inner, X in _bases_and_blocks(rng, n, w, b):
        Z, MZ = basis.workspace(b)
        Z[...] = X
        MZ[...] = inner.apply(X)
        tol = 10 * n * EPS * max(1.0, np.abs(X).max() ** 2)
        for Zi, MZi in ((Z, MZ), (X, inner.apply(X))):
            along, S = basis.residual_products(Zi, MZi)
            np.testing.assert_allclose(along, basis.MQ.T @ X, rtol=0, atol=tol)
            np.testing.assert_allclose(S, X.T @ inner.apply(X), rtol=0, atol=tol)
            np.testing.assert_array_equal(S, S.T)
        assert basis.width == w


@pytest.mark.parametrize("right_vectors", [True, False])
def test_a_zero_first_snapshot_keeps_the_block_on_the_gram_path(right_vectors):
    A = _pulses()
    A[:, ::40] = 0.0  # every block starts from a zero initial condition
    w = _weights(A.shape[0])
    sc = ss.StreamCompressor(A.shape[0], inner=w, target_error=1e-3, error_measure="mean_l2",
                             right_vectors=right_vectors)
    for j in range(0, A.shape[1], 40):
        rec = sc.absorb(A[:, j : j + 40])
        assert _by_gram(rec)
        if right_vectors:
            E = sc.expansion
            assert _mean_l2(A[:, : j + 40], E.U, E.V, w) <= sc.error_in_measure * (1 + 1e-9)
            # the zero snapshot is reconstructed as zero, to working accuracy
            top = np.sqrt(np.max(np.sum(w[:, np.newaxis] * A * A, axis=0)))
            assert np.sqrt(w @ (E.U @ E.V[j]) ** 2) <= 100 * A.shape[0] * EPS * top
    sc.finalize()
    assert sc.error_in_measure <= 1e-3


@pytest.mark.parametrize("weights", [None, "uniform", "varying"])
def test_a_wide_block_the_rounding_cannot_meet_is_refused_on_its_norms(weights, monkeypatch):
    """A block whose energy alone takes the Gram's rounding past the budget's growth is
    refused on its columns' norms, before its Gram, with the same result."""
    # beside a basis narrower than a slice the exact update takes such blocks in slices
    # without trying the Gram path; the check serves them beside a wider basis
    monkeypatch.setattr(stream_module, "skips_gram_path", lambda *a: False)
    made = _count_products(monkeypatch)
    A = _pulses(n=600, m=800)
    kw = {"target_error": 1e-9, "error_measure": "mean_l2"}
    if weights is not None:  # a diagonal M: weights, or a sparse diagonal matrix
        w = np.full(600, 0.25) if weights == "uniform" else _weights(600)
        kw["inner"] = sp.diags_array(w).tocsr() if weights == "uniform" else w
    fast = _stream(A, block=400, **kw)
    assert not any(_by_gram(r) for r in fast.history)
    assert made == []
    # without the check, the Gram is measured and the update refused after it
    import streamsvd.engine.update_gram as update_gram

    monkeypatch.setattr(update_gram, "_refused_by_norms", lambda *a, **k: False)
    slow = _stream(A, block=400, **kw)
    assert made and not any(_by_gram(r) for r in slow.history)
    np.testing.assert_array_equal(fast.amplitudes, slow.amplitudes)
    assert fast.error_bound == slow.error_bound



@pytest.mark.parametrize("block", [10, 40])
def test_a_block_refused_on_a_bound_of_its_energy_gives_the_same_result(block, monkeypatch):
    """With a relative target, a block small beside the energy absorbed is refused
    on ||M||_2 ||X||_F^2 (an upper bound of its energy, refused before its products):
    every block so refused is one the measured check refuses, so the stream is the same
    to the last bit, with fewer products."""
    import streamsvd.engine.update_gram as update_gram

    n = 600
    h = 1.0 / n  # a P1 mass matrix: its rows sum to h, its largest eigenvalue below
    M = sp.diags_array([np.full(n - 1, h / 6), np.full(n, 4 * h / 6), np.full(n - 1, h / 6)],
                       offsets=[-1, 0, 1]).tocsr()
    A = _pulses(n=n, m=400) * np.exp(-np.linspace(0.0, 12.0, 400))  # a decaying pulse
    kw = {"target_error": 1e-4, "error_measure": "relative", "inner": M}
    made = _count_products(monkeypatch)
    fast = _stream(A, block=block, **kw)
    early = len(fast.history) - len(made)
    assert early > 0  # some blocks were refused before their products
    made.clear()
    monkeypatch.setattr(update_gram, "_refused_by_frobenius", lambda *a, **k: False)
    slow = _stream(A, block=block, **kw)
    assert len(made) == len(slow.history) > len(fast.history) - early
    assert [_by_gram(r) for r in fast.history] == [_by_gram(r) for r in slow.history]
    np.testing.assert_array_equal(fast.amplitudes, slow.amplitudes)
    np.testing.assert_array_equal(fast.left_vectors, slow.left_vectors)
    assert fast.error_bound == slow.error_bound
