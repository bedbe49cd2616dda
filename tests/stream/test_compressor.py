"""StreamCompressor: agreement with a dense model, error bound, hard streams, bad input."""

import math

import numpy as np
import pytest
import scipy.sparse
from hypothesis import settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, invariant, precondition, rule

import streamsvd as ss
from streamsvd.testing import assert_svd_contract, with_spectrum
from tests._examples import examples

EPS = np.finfo(float).eps


def stream(A, block, **kw):
    sc = ss.StreamCompressor(A.shape[0], **kw)
    for j in range(0, A.shape[1], block):
        sc.absorb(A[:, j : j + block])
    return sc


@pytest.mark.parametrize("block", [1, 7, 50, 400])
@pytest.mark.parametrize("rule", ["paper", "jacobi"])
def test_converged_stream_is_the_svd_of_everything_seen(rng, block, rule):
    A = with_spectrum(np.logspace(0, -10, 40), 120, 90, rng)
    sc = stream(A, block, rule=rule, sweeps=None)
    assert sc.n_seen == 90
    # right vectors of terms near eps * sigma_1 are determined only in the absolute sense
    # (V carries the amplitudes): checked by the coupling ratio, not LAPACK's relative one
    assert_svd_contract(A, sc.expansion, relative_v=False)


@pytest.mark.parametrize("sweeps", [1, 2])
def test_partial_sweeps_keep_the_product_exact_and_the_basis_orthonormal(rng, sweeps):
    A = with_spectrum(np.logspace(0, -6, 30), 80, 60, rng)
    sc = stream(A, 6, sweeps=sweeps)
    e = sc.expansion
    assert np.linalg.norm(A - e.to_dense()) <= 50 * 80 * EPS * np.linalg.norm(A)
    assert e.orthogonality_error() <= 50 * 80 * EPS
    # the monitor computed on the small Gram equals the true loss of orthogonality
    assert sc.orthogonality_error() == pytest.approx(e.orthogonality_error(), rel=0.1, abs=10 * EPS)


@pytest.mark.parametrize("order", ["forward", "reversed", "shuffled"])
def test_column_order_does_not_matter_untruncated(rng, order):
    A = with_spectrum(np.logspace(0, -8, 25), 60, 70, rng)
    perm = {"forward": np.arange(70), "reversed": np.arange(70)[::-1],
            "shuffled": np.random.default_rng(3).permutation(70)}[order]
    sc = stream(A[:, perm], 9, rule="jacobi", sweeps=None)
    s = np.linalg.svd(A, compute_uv=False)
    np.testing.assert_allclose(sc.expansion.amplitudes[:25], s[:25], rtol=0, atol=50 * 70 * EPS * s[0])


@pytest.mark.parametrize("order", ["forward", "reversed", "shuffled"])
def test_truncated_stream_is_near_optimal_and_bounded(rng, order):
    s = np.logspace(0, -5, 40)
    A = with_spectrum(s, 100, 120, rng)
    perm = {"forward": np.arange(120), "reversed": np.arange(120)[::-1],
            "shuffled": np.random.default_rng(4).permutation(120)}[order]
    k = 10
    sc = stream(A[:, perm], 10, rule="jacobi", sweeps=None, max_rank=k)
    assert sc.rank == k + 10  # max_rank + oversampling while streaming
    sc.finalize()
    e = sc.expansion
    assert e.rank == k
    err = np.linalg.norm(A[:, perm] - e.to_dense())
    optimal = math.sqrt(np.sum(s[k:] ** 2))
    assert err <= sc.error_bound * (1 + 1e-9) + 1e-12
    assert err <= 1.25 * optimal
    # the top singular values are those of the data to within sigma_{k+1}
    assert np.all(np.abs(e.amplitudes - s[:k]) <= 1.25 * s[k])


@pytest.mark.parametrize("rule,sweeps", [("paper", 1), ("jacobi", 1), ("paper", 3), ("jacobi", None)])
@pytest.mark.parametrize("trunc", [{"eps": 1e-3}, {"rtol": 1e-4}, {"max_rank": 8}])
def test_error_bound_is_guaranteed(rng, rule, sweeps, trunc):
    A = with_spectrum(np.logspace(0, -7, 50), 70, 150, rng)
    sc = ss.StreamCompressor(70, rule=rule, sweeps=sweeps, **trunc)
    for j in range(0, 150, 5):
        sc.absorb(A[:, j : j + 5])
        seen = A[:, : j + 5]
        err = np.linalg.norm(seen - sc.expansion.to_dense())
        assert err <= sc.error_bound + 100 * 70 * EPS * np.linalg.norm(seen)
        # never worse than the triangle inequality over the discarded energies
        tri = sum(r.discarded for r in sc.history)
        assert sc.error_bound <= tri * (1 + 1e-12) + 1e-300
    assert sc.discarded_energy > 0


def test_bound_is_pythagorean_when_truncating_at_convergence(rng):
    A = with_spectrum(np.logspace(0, -7, 50), 70, 150, rng)
    sc = stream(A, 10, rule="jacobi", sweeps=None, max_rank=12)
    assert sc.error_bound == pytest.approx(math.sqrt(sc.discarded_energy), rel=1e-6)
    err = np.linalg.norm(A - sc.expansion.to_dense())
    assert err == pytest.approx(sc.error_bound, rel=1e-3)


def test_repeated_snapshot_keeps_rank_one(rng):
    x = rng.standard_normal(50)
    sc = ss.StreamCompressor(50)
    for _ in range(1000):
        sc.absorb(x[:, None])
    assert sc.rank == 1 and sc.n_seen == 1000
    assert sc.expansion.amplitudes[0] == pytest.approx(np.linalg.norm(x) * math.sqrt(1000), rel=1e-12)
    assert sc.orthogonality_error() <= 50 * 50 * EPS


def test_snapshots_in_the_span_add_no_direction(rng):
    B = rng.standard_normal((40, 5))
    sc = ss.StreamCompressor(40)
    sc.absorb(B)
    rec = sc.absorb(B @ rng.standard_normal((5, 30)))
    assert rec.new_directions == 0 and rec.rejected == 30 and sc.rank == 5


@pytest.mark.parametrize("size,kept", [(1e-15, False), (1e-12, True), (1e-8, True)])
def test_tiny_new_directions(rng, size, kept):
    n = 60  # reject_tol = n eps = 1.3e-14
    B = np.linalg.qr(rng.standard_normal((n, 4)))[0]
    sc = ss.StreamCompressor(n, rule="jacobi", sweeps=None)
    sc.absorb(B)
    x = B @ [1.0, -1.0, 2.0, 0.5] + size * np.linalg.qr(rng.standard_normal((n, 5)))[0][:, 4]
    sc.absorb(x[:, None])
    assert sc.rank == (5 if kept else 4)
    assert sc.orthogonality_error() <= 50 * n * EPS
    A = np.column_stack([B, x])
    assert np.linalg.norm(A - sc.expansion.to_dense()) <= 10 * n * EPS * np.linalg.norm(A)


def test_nearly_parallel_snapshots(rng):
    x = rng.standard_normal(30)
    cols = [x + 1e-9 * k * rng.standard_normal(30) for k in range(20)]
    A = np.column_stack(cols)
    sc = stream(A, 1, rule="jacobi", sweeps=None)
    assert_svd_contract(A, sc.expansion, relative_v=False)


def test_amplitudes_from_1e_minus150_to_1e150(rng):
    A = rng.standard_normal((30, 12)) * np.logspace(-150, 150, 12)
    sc = stream(A, 1, rule="jacobi", sweeps=None)
    e = sc.expansion
    assert np.all(np.isfinite(e.V)) and e.orthogonality_error() <= 50 * 30 * EPS
    # every column is reproduced to its own relative accuracy
    rel = np.linalg.norm(A - e.to_dense(), axis=0) / np.linalg.norm(A, axis=0)
    assert rel[-1] <= 50 * 30 * EPS


def test_geometric_spectrum_to_1e_minus20(rng):
    A = with_spectrum(np.logspace(0, -20, 30), 50, 60, rng)
    sc = stream(A, 4, rule="jacobi", sweeps=None)
    assert_svd_contract(A, sc.expansion, relative_v=False)


def test_rank_cap_below_true_rank_keeps_best_directions(rng):
    s = np.r_[10.0, 5.0, 1e-6 * np.ones(20)]
    A = with_spectrum(s, 40, 60, rng)
    for oversampling in (0, 10):
        sc = stream(A, 3, rule="jacobi", sweeps=None, max_rank=2, oversampling=oversampling)
        sc.finalize()
        np.testing.assert_allclose(sc.expansion.amplitudes, s[:2], rtol=1e-6)


@pytest.mark.slow
def test_long_stream_orthogonality_stays_flat(rng):
    n = 40
    sc = ss.StreamCompressor(n, max_rank=6, rule="jacobi")
    worst = 0.0
    for _ in range(3000):
        sc.absorb(rng.standard_normal((n, 1)))
        worst = max(worst, sc.history[-1].orthogonality)
    assert worst <= 50 * n * EPS
    assert sc.expansion.orthogonality_error() <= 50 * n * EPS


def test_weighted_stream_is_M_orthonormal(rng):
    n = 35
    w = rng.uniform(0.5, 3.0, n)
    A = with_spectrum(np.logspace(0, -5, 12), n, 40, rng)
    sc = stream(A, 5, inner=w, rule="jacobi", sweeps=None)
    e = sc.expansion
    assert np.linalg.norm(e.U.T @ (w[:, None] * e.U) - np.eye(e.rank), 2) <= 50 * n * EPS * 6
    s = np.linalg.svd(np.sqrt(w)[:, None] * A, compute_uv=False)
    np.testing.assert_allclose(e.amplitudes[:12], s[:12], rtol=1e-10)


def test_zero_block_adds_rows_and_nothing_else(rng):
    sc = ss.StreamCompressor(20)
    sc.absorb(rng.standard_normal((20, 4)))
    before = sc.expansion
    sc.absorb(np.zeros((20, 3)))
    after = sc.expansion
    assert after.rank == before.rank and sc.n_seen == 7
    np.testing.assert_array_equal(after.V[4:], 0.0)


def _snapshot(sc):
    s = sc._life.state
    # the Gram is None while pending (after the Gram path): then it stays None
    arrays = (s.basis.Q, s.coords, np.zeros(0) if s.gram is None else s.gram, s.rows.V0,
              s.rows.Vp, s.R)
    return [a.copy() for a in arrays], sc.error_bound, len(sc.history), s.gram is None


@pytest.mark.parametrize(
    "bad,exc,match",
    [(np.full((20, 2), np.nan), ss.NonFiniteError, r"`columns` must be finite"),
     (np.ones((19, 2)), ss.ShapeMismatchError, r"`columns` must have 20 rows; got 19 \(shape \(19, 2\)\)\. Pass snapshots as columns"),
     (np.ones((20, 2), dtype=complex), ss.InputError, r"`columns` must be real; got complex"),
     (np.array([["x"] * 2] * 20), ss.InputError, r"`columns` must hold real numbers"),
     (np.ones((20, 0)), ss.InputError, r"`columns` must not be empty; got shape \(20, 0\)"),
     (np.ones(20), ss.ShapeMismatchError, r"`columns` must be 2-D; got 1-D")],
)
def test_bad_blocks_leave_the_state_bitwise_unchanged(rng, bad, exc, match):
    A = rng.standard_normal((20, 12))
    sc = ss.StreamCompressor(20)
    sc.absorb(A[:, :6])
    state = _snapshot(sc)
    with pytest.raises(exc, match=match):
        sc.absorb(bad)
    after = _snapshot(sc)
    assert all(np.array_equal(a, b) for a, b in zip(state[0], after[0], strict=True))
    assert state[1:] == after[1:]
    # the next valid block gives the same result as if the bad one had never come
    sc.absorb(A[:, 6:])
    ref = ss.StreamCompressor(20)
    ref.absorb(A[:, :6])
    ref.absorb(A[:, 6:])
    np.testing.assert_array_equal(sc.expansion.U, ref.expansion.U)
    np.testing.assert_array_equal(sc.expansion.V, ref.expansion.V)


@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("options", [
    dict(max_rank=4),
    dict(target_error=1e-3, error_measure="relative"),
    dict(target_error=1e-3, error_measure="mean_l2", inner=np.linspace(1e-3, 2.0, 20)),
    dict(max_rank=4, inner=scipy.sparse.diags([-0.4, 1.0, -0.4], [-1, 0, 1], shape=(20, 20),
                                              format="csr")),
])
def test_the_gram_path_refuses_a_non_finite_entry(rng, value, options):
    """The Gram path checks the block from its Gram's diagonal; one bad entry anywhere,
    in the first or the last row, is refused with the state bitwise unchanged."""
    U = np.linalg.qr(rng.standard_normal((20, 20)))[0]
    V = np.linalg.qr(rng.standard_normal((30, 20)))[0]
    A = (U * np.logspace(0, -2, 20)) @ V.T
    sc = ss.StreamCompressor(20, **options)
    sc.absorb(A[:, :10])
    sc.absorb(A[:, 10:20])
    assert sc.history[-1].passes == 2  # the Gram path
    state = _snapshot(sc)
    for row in (0, 19):
        bad = A[:, 20:].copy()
        bad[row, 7] = value
        with pytest.raises(ss.NonFiniteError, match=r"`columns` must be finite; got 1 NaN or "
                           rf"infinite entries, the first at index \({row}, 7\)"):
            sc.absorb(bad)
        after = _snapshot(sc)
        assert all(np.array_equal(a, b) for a, b in zip(state[0], after[0], strict=True))
        assert state[1:] == after[1:]
    sc.absorb(A[:, 20:])
    assert sc.n_seen == 30 and sc.history[-1].passes == 2


@pytest.mark.parametrize("value", [np.nan, np.inf])
@pytest.mark.parametrize("layout", ["C", "F"])
@pytest.mark.parametrize("scale", [1.0, 1e300])
def test_the_exact_path_refuses_a_non_finite_entry(rng, value, layout, scale):
    """The exact path checks the block from the peaks its scaling takes, whichever the
    layout (a column-major block is scaled in place of a copy); a first block and a later
    one are refused with the state bitwise unchanged."""
    U = np.linalg.qr(rng.standard_normal((20, 20)))[0]
    V = np.linalg.qr(rng.standard_normal((30, 20)))[0]
    A = scale * (U * np.logspace(0, -2, 20)) @ V.T
    sc = ss.StreamCompressor(20)

    def bad_block(cols, row):
        bad = np.array(A[:, cols], order=layout)
        bad[row, 5] = value
        return bad

    for row in (0, 19):
        with pytest.raises(ss.NonFiniteError, match=r"`columns` must be finite; got 1 NaN or "
                           rf"infinite entries, the first at index \({row}, 5\)"):
            sc.absorb(bad_block(slice(0, 10), row))
        assert sc.n_seen == 0 and sc.rank == 0
    sc.absorb(A[:, :10])
    state = _snapshot(sc)
    for row in (0, 19):
        with pytest.raises(ss.NonFiniteError, match=rf"the first at index \({row}, 5\)"):
            sc.absorb(bad_block(slice(10, 20), row))
        after = _snapshot(sc)
        assert all(np.array_equal(a, b) for a, b in zip(state[0], after[0], strict=True))
        assert state[1:] == after[1:]
    sc.absorb(np.array(A[:, 10:20], order=layout))
    assert sc.n_seen == 20 and sc.history[-1].passes != 2  # the exact path


def test_add_checks_shapes(rng):
    sc = ss.StreamCompressor(10)
    sc.add(rng.standard_normal((10, 2)), rng.standard_normal((7, 2)))
    with pytest.raises(ss.ShapeMismatchError, match=r"`V_k` must have 7 rows"):
        sc.add(rng.standard_normal((10, 2)), rng.standard_normal((8, 2)))
    with pytest.raises(ss.ShapeMismatchError, match=r"`V_k` must have 2 columns"):
        sc.add(rng.standard_normal((10, 2)), rng.standard_normal((7, 3)))


@pytest.mark.parametrize(
    "kwargs,match",
    [({"n": 0}, r"`n` must be an integer >= 1; got int 0"),
     ({"n": 5, "sweeps": 0}, r"`sweeps` must be an integer >= 1 or None"),
     ({"n": 5, "rule": "x"}, r"`rule` must be one of"),
     ({"n": 5, "rtol": -1}, r"`rtol` must be a finite number >= 0"),
     ({"n": 5, "max_rank": 2.5}, r"`max_rank` must be an integer >= 1 or None"),
     ({"n": 5, "inner": np.ones(4)}, r"`inner` acts on vectors of size 4")],
)
def test_bad_options(kwargs, match):
    with pytest.raises(ss.InputError, match=match):
        ss.StreamCompressor(**kwargs)


class StreamModel(RuleBasedStateMachine):
    """Absorb random blocks and add random increments; compare with a dense model."""

    def __init__(self):
        super().__init__()
        self.n = 15
        self.sc = ss.StreamCompressor(self.n, rule="jacobi", sweeps=1)
        self.A = np.zeros((self.n, 0))

    @rule(b=st.integers(1, 6), seed=st.integers(0, 2**16), rank=st.integers(1, 4))
    def absorb(self, b, seed, rank):
        r = np.random.default_rng(seed)
        B = r.standard_normal((self.n, rank)) @ r.standard_normal((rank, b))
        self.sc.absorb(B)
        self.A = np.concatenate([self.A, B], axis=1)

    @precondition(lambda self: self.A.shape[1] > 0)
    @rule(k=st.integers(1, 3), seed=st.integers(0, 2**16))
    def add(self, k, seed):
        r = np.random.default_rng(seed)
        Uk, Vk = r.standard_normal((self.n, k)), r.standard_normal((self.A.shape[1], k))
        self.sc.add(Uk, Vk)
        self.A = self.A + Uk @ Vk.T

    @invariant()
    def matches_dense_model(self):
        if self.A.shape[1] == 0:
            return
        e = self.sc.expansion
        scale = np.linalg.norm(self.A)
        assert np.linalg.norm(self.A - e.to_dense()) <= 200 * self.n * EPS * max(scale, 1e-300)
        assert e.orthogonality_error() <= 50 * self.n * EPS
        assert np.all(np.diff(e.amplitudes) <= 0)


TestStreamModel = StreamModel.TestCase
TestStreamModel.settings = settings(max_examples=examples(30), stateful_step_count=15, deadline=None)


@pytest.mark.parametrize("sweeps,max_rank", [(None, 12), (1, 12), (None, None)])
def test_tree_merge_equals_the_stream_and_composes_the_bound(rng, sweeps, max_rank):
    s = np.logspace(0, -8, 40)
    A = with_spectrum(s, 90, 160, rng)
    leaves = []
    for j in range(0, 160, 40):
        sc = ss.StreamCompressor(90, rule="jacobi", sweeps=sweeps, max_rank=max_rank)
        for k in range(j, j + 40, 10):
            sc.absorb(A[:, k : k + 10])
        leaves.append(sc)
    while len(leaves) > 1:
        for a, b in zip(leaves[::2], leaves[1::2], strict=True):
            a.merge(b)
        leaves = leaves[::2]
    root = leaves[0]
    assert root.n_seen == 160 and root.history[-1].kind == "merge"
    err = np.linalg.norm(A - root.expansion.to_dense())
    assert err <= root.error_bound + 100 * 90 * EPS * np.linalg.norm(A)
    assert root.orthogonality_error() <= 50 * 90 * EPS
    if max_rank is None:
        assert_svd_contract(A, ss.compress(root.expansion, rule="jacobi").expansion, relative_v=False)
    elif sweeps is None:
        assert err <= 1.25 * math.sqrt(np.sum(s[max_rank:] ** 2))


def test_merge_refuses_other_sizes_and_inner_products(rng):
    a = ss.StreamCompressor(10)
    with pytest.raises(ss.InputError, match=r"`other` must have snapshots of size 10; got 11"):
        a.merge(ss.StreamCompressor(11))
    with pytest.raises(ss.InnerProductMismatchError, match=r"`other` uses the inner product"):
        a.merge(ss.StreamCompressor(10, inner=np.full(10, 2.0)))
    with pytest.raises(ss.InputError, match=r"`other` must be a StreamCompressor or an Expansion; got ndarray"):
        a.merge(np.eye(10))
    a.merge(ss.Expansion(np.eye(10)[:, :2], rng.standard_normal((4, 2))))
    assert a.n_seen == 4 and a.rank == 2


def test_add_with_coefficients_in_the_basis_matches_the_dense_model(rng):
    n, m = 30, 25
    sc = ss.StreamCompressor(n, rule="jacobi", sweeps=1)
    A = np.zeros((n, m))
    Uk, Vk = rng.standard_normal((n, 4)), rng.standard_normal((m, 4))
    sc.add(Uk, Vk)
    A += Uk @ Vk.T
    for step in range(6):
        U = sc.expansion.U
        dV = rng.standard_normal((m, sc.rank))
        u = rng.standard_normal((n, step % 2))
        v = rng.standard_normal((m, step % 2))
        rec = sc.add(u, v, coefficients=dV)
        A += U @ dV.T + u @ v.T
        assert rec.new_directions == step % 2
        assert np.linalg.norm(A - sc.expansion.to_dense()) <= 200 * n * EPS * np.linalg.norm(A)
        assert sc.orthogonality_error() <= 50 * n * EPS
    p = sc.rank
    with pytest.raises(ss.ShapeMismatchError,
                       match=rf"`coefficients` must have {p} columns; got {p + 1} \(shape \({m}, {p + 1}\)\)"):
        sc.add(np.zeros((n, 0)), np.zeros((m, 0)), coefficients=np.zeros((m, p + 1)))
    with pytest.raises(ss.InputError, match=r"`U_k` must have at least one column \(or pass `coefficients`\)"):
        sc.add(np.zeros((n, 0)), np.zeros((m, 0)))


def test_the_facade_holds_its_parts_and_forwards_every_public_name_of_theirs():
    """StreamCompressor inherits from nothing; each public name of a part is the facade's,
    with the part's docstring, and reads the same object; the tall mode is a factory."""
    from streamsvd.parallel.tall import TallCompressor
    from streamsvd.stream.updates import Updates
    from streamsvd.stream.view import ExpansionView
    from streamsvd.stream.window import Window

    assert ss.StreamCompressor.__mro__ == (ss.StreamCompressor, object)
    among_parts = {"remove_positions", "windowed", "internal_coefficients",
                   "warn_if_target_missed"}  # what one part asks of another
    for part in (Updates, Window, ExpansionView):
        for name in (n for n in vars(part) if not n.startswith("_") and n not in among_parts):
            assert getattr(ss.StreamCompressor, name).__doc__ == getattr(part, name).__doc__, name
    sc = ss.StreamCompressor(8, max_rank=2)
    sc.absorb(np.arange(24.0).reshape(8, 3))
    assert sc.rank == sc._view.rank and sc.n_absorbed == 3 and sc.chunk_rows is None
    tc = TallCompressor(8, chunk_rows=4)
    try:
        assert type(tc) is ss.StreamCompressor and isinstance(tc, TallCompressor)
        assert not isinstance(sc, TallCompressor) and tc.chunk_rows == 4
    finally:
        tc.close()
