"""Each hole the error bound had, as a case that must hold."""

import numpy as np
import pytest

import streamsvd as ss

EPS = np.finfo(float).eps


def test_bound_holds_after_a_merge_that_rejects():
    n = 6
    e = np.eye(n)
    kw = {"reject_tol": 0.1, "max_rank": 2, "oversampling": 0, "rule": "jacobi",
          "sweeps": None}
    a = ss.StreamCompressor(n, **kw)
    a.absorb(e[:, [0]])
    b = ss.StreamCompressor(n, **kw)
    b.absorb(np.column_stack([10 * e[:, 2], e[:, 0] + 0.5 * e[:, 1]]))  # 0.5 e2 rejected
    a.merge(b)
    assert a.history[-1].rejected == 1
    a.absorb((e[:, 0] - e[:, 1])[:, None])
    A = np.column_stack([e[:, 0], 10 * e[:, 2], e[:, 0] + 0.5 * e[:, 1], e[:, 0] - e[:, 1]])
    assert np.linalg.norm(A - a.expansion.to_dense()) <= a.error_bound * (1 + 1e-12)


def test_weighted_increment_at_1e200_keeps_its_directions(rng):
    n = 50
    w = rng.uniform(0.5, 2.0, n)
    sc = ss.StreamCompressor(n, inner=w)
    sc.absorb(rng.standard_normal((n, 3)))
    sc.add(rng.standard_normal((n, 2)) * 1e200, rng.standard_normal((3, 2)))
    assert sc.rank == 5 and sc.history[-1].rejected == 0


def test_subnormal_columns_are_directions_not_a_dropped_block(rng):
    B = np.zeros((20, 3))
    B[:, 0] = rng.standard_normal(20) * 1e-310
    B[3, 1] = 5e-324  # the smallest subnormal
    B[:, 2] = rng.standard_normal(20) * 1e-300
    sc = ss.StreamCompressor(20)
    sc.absorb(B)
    assert sc.rank == 3 and sc.history[-1].rejected == 0
    assert np.array_equal(sc.expansion.to_dense()[3, 1], 5e-324)
    # beside a column of size 1, the same column is far below the rounding of the block
    # (eps ||A||, outside the bound's theorem): the block is still not dropped
    B[:, 2] = rng.standard_normal(20)
    sc = ss.StreamCompressor(20)
    sc.absorb(B)
    assert sc.rank >= 2


@pytest.mark.parametrize("scale", [1e200, 1e-200])
def test_compress_keeps_its_bound_at_extreme_scales(rng, scale):
    U = np.linalg.qr(rng.standard_normal((30, 8)))[0]
    V = rng.standard_normal((20, 8)) * np.logspace(0, -3, 8) * scale
    r = ss.compress(ss.Expansion(U, V), eps=0.05 * scale, rule="jacobi")
    err = np.linalg.norm((U @ V.T - r.expansion.to_dense()) / scale) * scale
    assert r.expansion.rank < 8 and np.isfinite(r.error_bound)
    assert err <= r.error_bound * (1 + 1e-12)
    assert r.error_bound <= err * (1 + 1e-12)


def test_discarded_energy_of_residuals_rejected_in_different_blocks_is_exact(rng):
    n = 200
    x = rng.standard_normal(n)
    U = x[:, None] + 1e-4 * rng.standard_normal((n, 130))  # 130 columns: three blocks
    V = np.ones((7, 130))
    g = ss.orthonormalize(U, V, reject_tol=1e-3)
    true = np.linalg.norm(U @ V.T - g.expansion.to_dense()) ** 2
    assert g.expansion.rank == 1 and len(g.rejected) == 129
    assert abs(g.discarded_energy - true) <= 1e-10 * true


def test_the_bound_account_is_stored_whole_and_read_from_older_stores():
    from streamsvd.engine.bound import Bound
    from streamsvd.stream.persistence import _Small

    b = Bound(3.0, np.inf, 2.0, 0.5, 1.5)
    small = _Small(coords=np.eye(2), gram=np.eye(2), R=np.ones((2, 3)), Vp=None, bound=b,
                   source_offset=7, m=3, wasted_flops=1.0)
    flat, layout = small.pack()
    back = _Small.unpack(flat, layout, pending=False)
    assert back.bound == b and (back.source_offset, back.m) == (7, 3)
    # a store written before kept three floats of the account, then offset, m, flops
    old = flat[: flat.size - 2]
    layout = [*layout[:-1], [6]]
    back = _Small.unpack(old, layout, pending=False)
    assert back.bound == Bound(3.0, np.inf, 2.0, np.inf, 2.0)  # k <= c, rho <= discarded
    assert (back.source_offset, back.m, back.wasted_flops) == (7, 3, 1.0)


def test_small_rejections_beside_converged_cuts_add_by_their_own_norm():
    from streamsvd.engine.bound import Bound

    # converged cuts (no coupling) after residuals of norm 1e-6 were rejected: the cross
    # term is at most rho d, not d b
    b = Bound(1.0, 10.0, 1.0, 0.0, 1e-6)
    after = float(b.after(np.array([0.5]), overlapping=False)[0])
    assert after == pytest.approx(np.sqrt(1.0 + 0.25 + 2 * 1e-6 * 0.5), rel=1e-15)
    assert b.step(0.5, 0.0, overlapping=False).bound == after
