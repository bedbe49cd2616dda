"""bench/brand.py: Brand's incremental SVD and its tuned variant on rank-deficient streams."""

import importlib
from pathlib import Path

import numpy as np
import pytest

BENCH = Path(__file__).resolve().parents[3] / "bench"


@pytest.fixture
def brand(monkeypatch):
    monkeypatch.syspath_prepend(str(BENCH))
    return importlib.import_module("brand")


def _stream(cls, A, *, rank, block):
    n, m = A.shape
    svd = cls(n, rank=rank, max_columns=m, max_block=block)
    for j in range(0, m, block):
        svd.absorb(A[:, j : j + block])
    return svd


@pytest.mark.parametrize("rank", [60, 100, 150])
@pytest.mark.parametrize("name", ["BrandSVD", "TunedBrandSVD"])
def test_rank_deficient_residual(brand, rank, name):
    # 400 x 200 of exact rank 100 in blocks of 100: the second block's residual is rank
    # deficient (rank 40 under a cap of 60, numerically zero under a cap >= 100)
    rng = np.random.default_rng(3)
    A = rng.standard_normal((400, 100)) @ rng.standard_normal((100, 200))
    svd = _stream(getattr(brand, name), A, rank=rank, block=100)
    s = np.linalg.svd(A, compute_uv=False)
    err = np.linalg.norm(A - (svd.U * svd.s) @ svd.V.T)
    assert np.linalg.norm(svd.U.T @ svd.U - np.eye(svd.p)) < 1e-12
    assert np.all(np.isfinite(svd.s)) and np.all(np.diff(svd.s) <= 0.0)
    if rank >= 100:
        assert err < 1e-12 * s[0]
        assert np.max(np.abs(svd.s[:100] - s[:100])) < 1e-12 * s[0]
    else:
        # one truncation at the exact SVD of block 1 and of the final expansion: the
        # reported bound is the error, to rounding
        assert svd.error_bound == pytest.approx(err, rel=1e-8)
    ref = _stream(brand.BrandSVD, A, rank=rank, block=100)
    top = min(rank, 100)
    assert np.max(np.abs(svd.s[:top] - ref.s[:top])) < 1e-12 * s[0]


def test_tuned_keeps_a_graded_residual(brand):
    # singular values 1 to 1e-11 in one block: nothing is dropped, X = Q R to rounding
    rng = np.random.default_rng(4)
    Q1, _ = np.linalg.qr(rng.standard_normal((500, 40)))
    Q2, _ = np.linalg.qr(rng.standard_normal((40, 40)))
    s = np.logspace(0, -11, 40)
    A = (Q1 * s) @ Q2.T
    svd = _stream(brand.TunedBrandSVD, A, rank=40, block=40)
    assert svd.dropped == 0
    assert np.max(np.abs(svd.s - s)) < 1e-14
    assert np.linalg.norm(svd.U.T @ svd.U - np.eye(40)) < 1e-13


def test_tuned_zero_block(brand):
    rng = np.random.default_rng(5)
    A = np.hstack([rng.standard_normal((50, 5)), np.zeros((50, 5)), rng.standard_normal((50, 5))])
    svd = _stream(brand.TunedBrandSVD, A, rank=10, block=5)
    assert svd.p == 10
    np.testing.assert_allclose((svd.U * svd.s) @ svd.V.T, A, atol=1e-12)
