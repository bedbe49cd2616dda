"""Tests of streamsvd.linalg.slices: a wide block extended slice by slice."""

from __future__ import annotations

import numpy as np
import pytest

from streamsvd.algebra.inner import as_inner
from streamsvd.algebra.memory import MemoryBasis
from streamsvd.linalg.extend import extend_basis
from streamsvd.linalg.rejection import default_reject_tol
from streamsvd.linalg.slices import extend_in_slices, slice_width
from tests.linalg._snapshots import mass as _mass
from tests.linalg._snapshots import pulse as _pulse

EPS = np.finfo(np.float64).eps




def _norm(X, ip):
    return float(np.sqrt(max(np.sum(X * ip.apply(X)), 0.0)))


def test_blocks_of_two_slices_are_sliced_beside_a_basis_narrower_than_a_slice():
    assert slice_width(191, 0) is None
    assert slice_width(192, 0) == 96
    assert slice_width(1000, 95) == 96
    assert slice_width(1000, 96) is None


@pytest.mark.parametrize("scale", [0, 400, -400])
@pytest.mark.parametrize("first", [True, False])
@pytest.mark.parametrize("euclidean", [True, False])
def test_a_wide_block_in_slices_is_decomposed_exactly(euclidean, first, scale):
    n, b, w0 = 400, 200, 0 if first else 40
    A = np.ldexp(_pulse(n, w0 + b), scale)
    ip = as_inner(None if euclidean else _mass(n), n)
    basis = MemoryBasis(n, ip, capacity=2 * (w0 + b))
    gram = None
    if w0:
        ext0 = extend_basis(basis, None, A[:, :w0], inner=ip, reject_tol=default_reject_tol(n))
        basis.accept(ext0.rank)
        gram = basis.measure_gram()
    X = A[:, w0:]
    energy = _norm(np.ldexp(X, -scale), ip) ** 2
    budget = np.ldexp(1e-12 * energy, 2 * scale)
    w = basis.width
    ext = extend_in_slices(basis, None, X, inner=ip, reject_tol=default_reject_tol(n),
                           basis_gram=gram, aside=(budget, 0.0), width=50)
    r = ext.rank
    Q = basis.Q[:, :w].copy()
    Qn = basis.workspace(b)[0][:, :r].copy()
    MQn = ip.apply(Qn)
    # the new directions are M-orthonormal and M-orthogonal to the basis, as measured
    assert np.linalg.norm(Qn.T @ MQn - np.eye(r), 2) <= 100 * n * EPS
    assert np.linalg.norm(Q.T @ MQn) <= 100 * n * EPS
    np.testing.assert_allclose(ext.cross_gram, Q.T @ MQn, rtol=0, atol=100 * n * EPS)
    # X = Q coeffs + Q_new R_new + Res: the rejected norm is ||Res||, measured, and Res
    # is M-orthogonal to the basis and to the new directions
    res = np.ldexp(X, -scale) - Q @ np.ldexp(ext.coeffs, -scale) \
        - Qn @ np.ldexp(ext.R_new, -scale)
    rounding = 10 * n * EPS * np.sqrt(energy)
    reported = np.ldexp(ext.rejected_norm(), -scale)
    assert abs(_norm(res, ip) - reported) <= 1e-6 * reported + rounding
    assert np.linalg.norm(np.hstack([Q, Qn]).T @ ip.apply(res)) <= rounding
    # what was set aside fits the budget, up to the rounding of the slices' rejections
    assert reported**2 <= 1e-12 * energy * (1 + 1e-9) + rounding**2
    assert abs(np.ldexp(ext.block_norm, -scale) - np.sqrt(energy)) <= 1e-12 * np.sqrt(energy)
    # its norm is known for a block of snapshots only
    with pytest.raises(ValueError, match="columns' energies"):
        ext.rejected_norm(np.ones((2, b)))


@pytest.mark.parametrize("euclidean", [True, False])
def test_slices_that_keep_every_column_grow_their_directions_past_a_slice(euclidean):
    # independent columns: every slice keeps all its own, so the directions found
    # outgrow the first buffer (one slice) twice
    n, b, width = 300, 200, 50
    X = np.random.default_rng(5).standard_normal((n, b))
    ip = as_inner(None if euclidean else _mass(n), n)
    basis = MemoryBasis(n, ip, capacity=2 * b)
    ext = extend_in_slices(basis, None, X, inner=ip, reject_tol=default_reject_tol(n),
                           basis_gram=None, aside=(1e-30, 0.0), width=width)
    assert ext.rank == b
    Qn = basis.workspace(b)[0][:, :b].copy()
    assert np.linalg.norm(Qn.T @ ip.apply(Qn) - np.eye(b), 2) <= 100 * n * EPS
    scale = np.linalg.norm(X, 2)
    np.testing.assert_allclose(Qn @ ext.R_new, X, rtol=0, atol=100 * n * EPS * scale)
    assert ext.rejected_norm() <= 100 * n * EPS * scale


def test_slices_find_the_span_the_whole_block_finds():
    n, b = 400, 240
    X = _pulse(n, b)
    ip = as_inner(_mass(n), n)
    budget = 1e-12 * _norm(X, ip) ** 2
    exts, spans = [], []
    for sliced in (False, True):
        basis = MemoryBasis(n, ip, capacity=2 * b)
        if sliced:
            ext = extend_in_slices(basis, None, X, inner=ip, reject_tol=default_reject_tol(n),
                                   basis_gram=None, aside=(budget, 0.0), width=60)
        else:
            ext = extend_basis(basis, None, X, inner=ip, reject_tol=default_reject_tol(n),
                               aside=(budget, 0.0))
        exts.append(ext)
        spans.append(basis.workspace(b)[0][:, :ext.rank].copy())
    # every direction the whole block keeps, beyond what it sets aside, lies in the span
    # the slices found, to the square root of the budget
    whole, sliced = spans
    left = whole - sliced @ (sliced.T @ ip.apply(whole))
    kept = whole @ exts[0].R_new  # the block as the whole extension keeps it
    lost = kept - sliced @ (sliced.T @ ip.apply(kept))
    assert _norm(lost, ip) <= 2 * np.sqrt(budget) + 100 * n * EPS * _norm(X, ip)
    assert left.shape[1] == exts[0].rank


@pytest.mark.parametrize("kind", ["panels", "store"])
def test_a_basis_in_panels_or_in_a_store_takes_wide_blocks_in_slices(tmp_path, kind):
    # the panels make a new workspace at every call: the slices keep their own
    from unittest import mock

    import streamsvd as ss
    import streamsvd.linalg.slices as slices_module
    from streamsvd.parallel.tall import tall_compress

    taken = []
    original = slices_module.extend_in_slices

    def spy(*args, **kwargs):
        taken.append(kwargs["width"])
        return original(*args, **kwargs)

    n, m = 1000, 400
    A = _pulse(n, m)
    kw = dict(target_error=1e-6, error_measure="relative", rule="jacobi", sweeps=None)
    with mock.patch.object(slices_module, "extend_in_slices", spy):
        if kind == "panels":
            sc = tall_compress(A, block=200, chunk_rows=300, **kw)
        else:
            sc = ss.StreamCompressor(n, store=tmp_path / "s.zarr", **kw)
            for j in range(0, m, 200):
                sc.absorb(A[:, j:j + 200])
        sc.finalize()
    assert taken
    U, V = sc.factors()
    err = np.linalg.norm(A - np.asarray(U) @ V.T)
    assert err <= sc.error_bound * (1 + 1e-9) + 50 * m * EPS * np.linalg.norm(A)
    assert sc.error_in_measure <= 1e-6
    sc.close()
