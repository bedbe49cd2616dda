"""Tests of streamsvd.linalg.sketch: the directions to keep found from a sketch of a block."""

from __future__ import annotations

import numpy as np
import pytest

import streamsvd as ss
from streamsvd.algebra.inner import as_inner
from streamsvd.algebra.memory import MemoryBasis
from streamsvd.linalg.extend import extend_basis
from streamsvd.linalg.rejection import default_reject_tol
from streamsvd.linalg.sketch import SKETCH_OVERSAMPLING, Sketch, plan_sketch
from tests.linalg._snapshots import mass as _mass
from tests.linalg._snapshots import pulse as _pulse

EPS = np.finfo(np.float64).eps
U64 = EPS / 2




def _energies(X, ip):
    return np.maximum(np.einsum("ij,ij->j", X, ip.apply(X)), 0.0)


def _extend(n, w0, X, ip, *, share, sketch, unit=U64):
    """A basis of the pulse's first w0 columns, extended by X with a budget of share."""
    basis = MemoryBasis(n, ip, capacity=2 * (w0 + X.shape[1]))
    A0 = _pulse(n, w0 + X.shape[1])[:, :w0]
    first = extend_basis(basis, None, A0, inner=ip, reject_tol=default_reject_tol(n))
    basis.accept(first.rank)
    gram = basis.measure_gram()
    budget = share * float(np.sum(_energies(X, ip)))
    ext = extend_basis(basis, None, X, inner=ip, reject_tol=default_reject_tol(n),
                       basis_gram=gram, aside=(budget, 0.0),
                       sketch=Sketch(sketch, unit) if sketch else None)
    return basis, ext, budget



def test_the_sketch_follows_an_update_that_kept_an_eighth_of_the_block_at_most():
    assert plan_sketch(None, 91, U64) is None
    assert plan_sketch(8, 91, U64) == Sketch(8 + SKETCH_OVERSAMPLING, U64)
    assert plan_sketch(0, 32, 2.0**-24) == Sketch(SKETCH_OVERSAMPLING, 2.0**-24)
    assert plan_sketch(11, 91, U64) == Sketch(11 + SKETCH_OVERSAMPLING, U64)
    assert plan_sketch(12, 91, U64) is None  # 12 > 91 / 8
    assert plan_sketch(2, 10, U64) is None


@pytest.mark.parametrize("scale", [0, 300, -300])
@pytest.mark.parametrize("euclidean", [True, False])
def test_a_block_extended_from_a_sketch_is_decomposed_exactly(euclidean, scale):
    n, w0, b = 500, 60, 90
    ip = as_inner(None if euclidean else _mass(n), n)
    X = np.ldexp(_pulse(n, w0 + b)[:, w0:], scale)
    basis, ext, budget = _extend(n, w0, X, ip, share=1e-10, sketch=16)
    assert ext.column_energies is not None and ext.skewed  # the sketch's extension
    r, w = ext.rank, basis.width
    assert 0 < r < 16
    Q = basis.Q[:, :w].copy()
    Qn = basis.workspace(b)[0][:, :r].copy()
    MQn = ip.apply(Qn)
    # the new directions are M-orthonormal, their Gram and their part along the basis
    # measured (a single projection leaves it, at most 2^-10 of their norm)
    assert np.linalg.norm(Qn.T @ MQn - np.eye(r), 2) <= 100 * n * EPS
    np.testing.assert_allclose(ext.gram_new, Qn.T @ MQn, rtol=0, atol=100 * n * EPS)
    np.testing.assert_allclose(ext.cross_gram, Q.T @ MQn, rtol=0, atol=100 * n * EPS)
    assert np.max(np.abs(ext.cross_gram)) <= 2.0**-10
    # X = Q coeffs + Q_new R_new + Res, Res M-orthogonal to the new directions, and each
    # column's reported energy is its residual's, measured, plus its share of the
    # allowance for the rounding (4 (sqrt(b n) + b) eps of the residual's energy)
    Xs = np.ldexp(X, -scale)
    res = Xs - Q @ np.ldexp(ext.coeffs, -scale) - Qn @ np.ldexp(ext.R_new, -scale)
    measured = _energies(res, ip)
    reported = np.ldexp(ext.column_energies, 2 * (ext.exponents - scale))
    total = float(np.sum(_energies(Xs, ip)))
    allowance = 4 * (np.sqrt(b * n) + b) * EPS * total
    rounding = 100 * n * EPS * total
    assert np.all(measured <= reported + rounding / b)
    assert float(np.sum(reported - measured)) <= allowance + rounding
    assert np.linalg.norm(Qn.T @ ip.apply(res)) <= 100 * n * EPS * np.sqrt(total)
    # what was set aside fits the budget (the columns the rule rejected add their n eps)
    assert float(np.sum(reported)) <= np.ldexp(budget, -2 * scale) + rounding
    assert ext.rejected_norm() == pytest.approx(
        np.ldexp(np.sqrt(np.sum(reported)), scale), rel=1e-6, abs=0)


@pytest.mark.parametrize("euclidean", [True, False])
def test_the_sketch_keeps_as_many_directions_as_the_residuals_gram(euclidean):
    n, w0, b = 500, 60, 90
    ip = as_inner(None if euclidean else _mass(n), n)
    X = _pulse(n, w0 + b)[:, w0:]
    ranks = [_extend(n, w0, X, ip, share=share, sketch=sketch)[1].rank
             for share in (1e-6, 1e-10) for sketch in (16, 0)]
    assert abs(ranks[0] - ranks[1]) <= 1 and abs(ranks[2] - ranks[3]) <= 1
    assert ranks[0] < ranks[2]  # a larger budget sets more aside


@pytest.mark.parametrize("share, sketch, unit", [(1e-40, 16, U64), (1e-10, 2, U64),
                                                 (1e-10, 16, 2.0**-11)])
def test_a_sketch_that_cannot_set_aside_enough_leaves_the_block_to_the_gram(share, sketch,
                                                                           unit):
    # a budget below the rounding allowance, a sketch narrower than the directions the
    # budget needs, or a budget within the rounding of the snapshots' own dtype (float16
    # here; at 1e-10 with float64 snapshots the sketch is taken, above): the residual's
    # Gram decides, on the block as it was
    n, w0, b = 500, 60, 90
    ip = as_inner(_mass(n), n)
    X = _pulse(n, w0 + b)[:, w0:]
    basis_s, ext_s, _ = _extend(n, w0, X, ip, share=share, sketch=sketch, unit=unit)
    basis_g, ext_g, _ = _extend(n, w0, X, ip, share=share, sketch=0)
    assert ext_s.column_energies is None
    for name in ("coeffs", "R_new", "rejected_map", "rejected_gram", "cross_gram", "gram_new"):
        np.testing.assert_array_equal(getattr(ext_s, name), getattr(ext_g, name), err_msg=name)
    r = ext_g.rank
    np.testing.assert_array_equal(basis_s.workspace(b)[0][:, :r], basis_g.workspace(b)[0][:, :r])


def _stream(A, b, M, target, *, store=None, upto=None, sc=None):
    sc = sc or ss.StreamCompressor(A.shape[0], inner=M, target_error=target,
                                   error_measure="mean_l2", rule="jacobi", sweeps=None,
                                   store=store)
    for j in range(0 if upto is None else upto[0], A.shape[1] if upto is None else upto[1], b):
        sc.absorb(A[:, j:j + b])
    return sc


@pytest.mark.parametrize("target", [1e-5, 1e-6])
def test_a_stream_with_sketches_keeps_its_bound_and_its_modes(target, monkeypatch, spy_on):
    import streamsvd.linalg.extend as extend_module

    n, b = 600, 90
    A = _pulse(n, 12 * b) * (1.0 + 0.3 * np.sin(np.arange(12 * b) / 7.0))
    M = _mass(n)
    taken = spy_on(extend_module, "extend_by_sketch")
    fast = _stream(A, b, M, target)
    assert len(taken) >= 4 and all(taken)  # every update that tried a sketch took it
    monkeypatch.setattr(extend_module, "extend_by_sketch", lambda *a, **k: None)
    slow = _stream(A, b, M, target)
    for sc in (fast, slow):
        sc.finalize()
        E = sc.expansion
        R = A - E.U @ E.V.T
        err = np.sqrt(np.sum(R * (M @ R)))
        assert err <= sc.error_bound * (1 + 1e-9)
        assert sc.error_bound <= target * np.sqrt(A.shape[1]) * (1 + 1e-12)
        U = sc.left_vectors
        assert np.linalg.norm(U.T @ (M @ U) - np.eye(U.shape[1]), 2) <= 100 * n * EPS
    assert abs(fast.rank - slow.rank) <= 1


def test_a_stream_resumed_from_its_store_repeats_its_sketches(tmp_path):
    # the sketch's width comes from the update before, which the store's history keeps,
    # and its test matrix is the same in every process
    n, b = 600, 90
    A = _pulse(n, 10 * b) * (1.0 + 0.3 * np.sin(np.arange(10 * b) / 7.0))
    M = _mass(n)
    whole = _stream(A, b, M, 1e-6)
    path = tmp_path / "s.zarr"
    _stream(A, b, M, 1e-6, store=path, upto=(0, 5 * b)).close(finalize=False)
    with ss.StreamCompressor.open(path) as again:
        _stream(A, b, M, 1e-6, sc=again, upto=(5 * b, 10 * b))
        np.testing.assert_array_equal(again.left_vectors, whole.left_vectors)
        assert again.error_bound == whole.error_bound
