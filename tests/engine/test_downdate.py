"""The small pieces of streamsvd.engine.downdate: the downdate itself, index intervals, ledger."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from streamsvd.engine.downdate import (
    EXACT_BELOW,
    LEDGER_SIZE,
    Ledger,
    downdate,
    intervals_add,
    intervals_contain,
    intervals_count_below,
    intervals_skip,
    physical_rows,
)
from tests._examples import examples

EPS = np.finfo(float).eps


@settings(max_examples=examples(30), deadline=None)
@given(seed=st.integers(0, 2**16), m=st.integers(12, 200), k=st.integers(1, 10),
       r=st.integers(1, 10))
def test_downdate_gives_an_orthonormal_factor_and_the_same_product(seed, m, k, r):
    rng = np.random.default_rng(seed)
    k = min(k, m - r)
    Y = np.linalg.qr(rng.standard_normal((m, k)))[0]
    R = rng.standard_normal((k, k + 2)) * np.logspace(0, -6, k + 2)
    J = rng.choice(m, size=r, replace=False)
    rest = np.setdiff1d(np.arange(m), J)
    d = downdate(Y[J], R)
    if d is None:  # a share below EXACT_BELOW: the caller orthonormalises the rows again
        Z = np.linalg.svd(Y[J], compute_uv=False)
        assert np.sqrt(1 - min(Z.max(), 1.0) ** 2) < EXACT_BELOW * (1 + 1e-12)
        return
    assert d.c_min >= EXACT_BELOW
    Y2 = Y[rest] @ d.S
    np.testing.assert_allclose(Y2 @ d.R, Y[rest] @ R, rtol=0,
                               atol=50 * m * EPS / d.c_min**2 * np.linalg.norm(R))
    # the orthogonality lost is about eps / c_min^2 (module docstring)
    assert np.linalg.norm(Y2.T @ Y2 - np.eye(Y2.shape[1]), 2) <= 50 * m * EPS / d.c_min**2


def test_downdate_declines_a_direction_living_in_the_removed_rows():
    # the third direction lives in row 2 only: its share is 0, so no small downdate
    Y = np.eye(6)[:, :3]
    R = np.diag([3.0, 2.0, 1.0])
    assert downdate(Y[[2]], R) is None
    # a share of 1e-8 is below what (1 - s)(1 + s) resolves: declined as well
    Y = np.linalg.qr(np.random.default_rng(0).standard_normal((6, 3)))[0]
    Y[:, 2] = np.array([1.0, 1e-8, 0, 0, 0, 0]) / np.hypot(1.0, 1e-8)
    Y = np.linalg.qr(Y[:, ::-1])[0][:, ::-1]
    assert downdate(Y[[0]], R) is None


def test_downdate_keeps_every_direction_when_the_shares_are_large():
    Y = np.linalg.qr(np.random.default_rng(1).standard_normal((40, 3)))[0]
    R = np.diag([3.0, 2.0, 1.0])
    d = downdate(Y[[5]], R)
    assert d is not None and d.R.shape == (3, 3)
    rest = np.delete(np.arange(40), 5)
    np.testing.assert_allclose((Y[rest] @ d.S) @ d.R, Y[rest] @ R, atol=100 * EPS)


@settings(max_examples=examples(50), deadline=None)
@given(removed=st.sets(st.integers(0, 60), max_size=30), probe=st.integers(0, 70))
def test_intervals_count_and_skip_are_inverse(removed, probe):
    iv = intervals_add(np.zeros((0, 2), dtype=np.int64), np.array(sorted(removed), dtype=int))
    held = np.array(sorted(removed), dtype=np.int64)
    g = np.array([probe])
    assert intervals_contain(iv, g)[0] == (probe in removed)
    assert intervals_count_below(iv, g)[0] == np.sum(held < probe)
    free = np.setdiff1d(np.arange(100), held)
    positions = np.arange(10)
    np.testing.assert_array_equal(intervals_skip(iv, positions), free[:10])
    # the stored rows of live positions skip the dead ones the same way
    np.testing.assert_array_equal(physical_rows(held, positions), free[:10])


def test_ledger_forgets_what_left_and_stays_small():
    led = Ledger.start(0, 0.0)
    for m in range(10, 1000, 10):
        led = led.appended(m, 1.0)
        assert led.entries.shape[0] <= LEDGER_SIZE
    total = led.total
    assert total == 99.0  # merging keeps the sum
    led = led.removed(np.arange(500))
    # entries whose prefix lay within the first 500 columns are gone, the others shortened
    assert 0 < led.total < total and np.all(led.entries[:, 0] > 0)
    assert led.scaled(0.5).total == 0.5 * led.total
    assert led.removed(np.arange(int(led.entries[:, 0].max()))).total == 0.0
