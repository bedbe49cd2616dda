"""The in-memory basis: the image ``M Q`` it stores is ``M`` applied to its columns.

Every product with the basis (projections, its Gram, the orthogonality measured from
it) reads ``M Q``; an image that drifts from its columns makes them all err together,
unseen by any of them.
"""

import numpy as np
import pytest
import scipy.sparse as sp

from streamsvd.algebra.inner import InnerProduct, as_inner
from streamsvd.algebra.memory import MemoryBasis

EPS = np.finfo(float).eps


class Opaque:
    """An inner product that says nothing of its cost (no ``entries_per_row``)."""

    is_euclidean = False

    def __init__(self, M):
        self.M, self.n, self.fingerprint = M, M.shape[0], "opaque"

    def apply(self, X):
        return self.M @ X

    def gram(self, X, Y):
        return X.T @ (self.M @ Y)


def _mass(kind, n, rng):
    """A badly scaled ``M``: weights over four decades, the mass matrix of linear elements
    whose sizes span five (sparse, dense, and behind an opaque object)."""
    if kind == "weights":
        return 10.0 ** rng.uniform(-2, 2, n)
    h = 10.0 ** rng.uniform(-5, 0, n + 1)
    M = sp.diags([h[1:-1] / 6, (h[:-1] + h[1:]) / 3, h[1:-1] / 6], [-1, 0, 1], format="csr")
    return {"sparse": M, "dense": M.toarray(), "opaque": Opaque(M.toarray())}[kind]


def _dense(inner, n):
    return inner.apply(np.eye(n))


@pytest.mark.parametrize("kind", ["weights", "sparse", "dense", "opaque"])
@pytest.mark.parametrize("in_place", [False, True])
def test_a_compaction_that_scales_weak_terms_up_keeps_the_image_of_its_columns(kind, in_place):
    """The Gram path writes ``[Q, X] W Lambda^(-1/2)``: a kept term 1e-12 of the largest
    in energy is scaled up by 2e5 to 4e5. Its image is ``M`` applied to the column written (to
    the rounding of one product with ``M``), not the old images combined (5e-11 to 1.3e-10
    off, relative: 3400 to 4800 times what is asserted), and
    the Gram the basis measures is its columns' own."""
    rng = np.random.default_rng(7)
    n, w, b = 60, 4, 6
    inner = as_inner(_mass(kind, n, rng), n)
    assert isinstance(inner, InnerProduct)
    M = _dense(inner, n)
    basis = MemoryBasis(n, inner, capacity=4, compact_in_place=in_place)
    L = np.linalg.cholesky(M)
    Y, MY = basis.workspace(w)
    Y[...] = np.linalg.solve(L.T, np.linalg.qr(rng.standard_normal((n, w)))[0])
    MY[...] = M @ Y
    basis.accept(w)
    # a block along the basis but for directions of 1e-3 .. 1e-7 of its norm
    X = basis.Q @ rng.standard_normal((w, b)) + np.linalg.solve(
        L.T, rng.standard_normal((n, b)) * np.logspace(-3, -7, b))
    S, C, H = basis.joint_products(np.asfortranarray(X))
    lam, W = np.linalg.eigh(np.block([[H, C], [C.T, S]]))
    keep = lam > 1e-13 * lam[-1]
    G = W[:, keep] / np.sqrt(lam[keep])
    assert np.max(np.abs(G)) > 1e5  # the weak kept terms are scaled up (2e5 to 4e5)
    gram = basis.compact_with_block(G)
    p = G.shape[1]
    basis.swap(p)
    Q, MQ = basis.Q, basis.MQ
    applied = np.abs(M) @ np.abs(Q)  # what one product with M rounds by, column by column
    err = np.linalg.norm(MQ - M @ Q, axis=0)
    assert np.all(err <= 4 * n * EPS * np.linalg.norm(applied, axis=0)), err
    if gram is None:  # measured by the next update
        gram = basis.measure_gram()
    truth = Q.T @ (M @ Q)
    scale = np.linalg.norm(np.abs(Q).T @ applied)
    assert np.linalg.norm(gram - truth) <= 4 * n * EPS * scale


@pytest.mark.parametrize("kind", ["sparse", "dense", "opaque"])
def test_a_compaction_that_scales_nothing_up_combines_the_images_when_cheaper(kind,
                                                                            monkeypatch):
    """An orthonormal rotation of the basis: the images are combined (no product with
    ``M``) when ``M`` costs more per entry than the combination (dense, or unknown), and
    ``M`` is applied when it costs less (a tridiagonal beside 8 columns)."""
    rng = np.random.default_rng(3)
    n, w = 60, 8
    inner = as_inner(_mass(kind, n, rng), n)
    M = _dense(inner, n)
    basis = MemoryBasis(n, inner, capacity=w)
    Y, MY = basis.workspace(w)
    Y[...] = np.linalg.solve(np.linalg.cholesky(M).T,
                             np.linalg.qr(rng.standard_normal((n, w)))[0])
    MY[...] = M @ Y
    basis.accept(w)
    applied = []
    monkeypatch.setattr("streamsvd.algebra.compaction.m_apply_into",
                        lambda inner, X, out: applied.append(X.shape[1]))
    basis.compact_planned(np.linalg.qr(rng.standard_normal((w, w)))[0], 0)
    assert applied == ([w] if kind == "sparse" else [])
