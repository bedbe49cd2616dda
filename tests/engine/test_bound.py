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
    assert after == pytest.approx(np.sqrt(1.0 + 0.25 + 2 * 1e-6 * 0.5), rel=1e-15,
                                  abs=0)
    assert b.step(0.5, 0.0, overlapping=False).bound == after


def test_the_cross_term_takes_the_cut_in_the_columns_before_the_update():
    """``o_t`` replaces ``d_t`` in the cross term, never past ``d_t``."""
    from streamsvd.engine.bound import Bound

    prior = Bound(bound=3.0, coupling_root=np.inf, discarded=2.0, cut_coupling_root=1.0,
                  rejected=2.0)
    d = np.array([0.5, 1.0, 4.0])
    whole = prior.after(d, overlapping=False)
    assert np.array_equal(prior.after(d, overlapping=False, before=d), whole)
    # k + o rho against o b: k^2 = 1, rho = 2, b = 3
    o = np.array([0.0, 0.25, 8.0])  # the last past d_t: taken as d_t
    expected = np.sqrt(9.0 + d**2 + 2 * np.minimum(np.minimum(o, d) * 3.0,
                                                    1.0 + np.minimum(o, d) * 2.0))
    np.testing.assert_allclose(prior.after(d, overlapping=False, before=o), expected,
                               rtol=4 * EPS)
    assert prior.step(1.0, 0.0, overlapping=False, discarded_before=0.0).bound == \
        pytest.approx(np.sqrt(9.0 + 1.0), rel=4 * EPS, abs=0)


@pytest.mark.parametrize("old_rows", [3, 12, 25])
def test_a_cut_is_measured_in_the_columns_before_the_update(rng, old_rows):
    """``CoreStep.cut_before`` is ``||K_old Z_cut||_F``, ``Z_cut`` the cut right singular
    vectors of ``K`` (the terms at convergence), LAPACK's."""
    from streamsvd.engine.core import core_step
    from streamsvd.engine.truncation import Truncation

    k, p = 30, 20
    K = (rng.standard_normal((k, p)) * np.logspace(0, -6, p)) @ np.linalg.qr(
        rng.standard_normal((p, p)))[0]
    step = core_step(K, rule="jacobi", sweeps=None, m=k, kind="absorb",
                     truncation=Truncation(max_rank=12), rows_before=K[:old_rows])
    Z = np.linalg.svd(K)[2].T
    expected = np.linalg.norm(K[:old_rows] @ Z[:, 12:])
    assert step.cut == 8
    assert abs(step.cut_before - expected) <= 50 * k * EPS * np.linalg.norm(K)
    assert step.cut_before <= step.cut_norm
    plain = core_step(K, rule="jacobi", sweeps=None, m=k, kind="absorb",
                      truncation=Truncation(max_rank=12))
    assert plain.cut_before is None


def test_float32_rounding_cut_where_it_arrived_meets_the_bound(rng, monkeypatch):
    """float32 snapshots near their precision: the cuts of each update fall mostly in its
    own columns (``o_t`` well under ``d_t``) and the error stays within the bound at every
    update, measured from the factors."""
    import streamsvd.engine.update as update

    steps = []
    core_step = update.core_step

    def recording(*args, **kwargs):
        step = core_step(*args, **kwargs)
        steps.append(step)
        return step

    monkeypatch.setattr(update, "core_step", recording)
    n, b = 400, 40
    t = np.linspace(0, 1, n)[:, None]
    blocks = []
    for j in range(6):  # trajectories of smooth pulses, rounded to float32
        c = rng.uniform(0.2, 0.8, b)
        w = 0.05 + 0.02 * j
        blocks.append(np.exp(-((t - c) / w) ** 2).astype(np.float32))
    A = np.hstack(blocks).astype(np.float64)
    sc = ss.StreamCompressor(n, target_error=3e-7, error_measure="mean_l2", rule="jacobi",
                             sweeps=None)
    seen = 0
    for X in blocks:
        sc.absorb(X)
        seen += X.shape[1]
        err = np.linalg.norm(A[:, :seen] - sc.expansion.to_dense())
        assert err <= sc.error_bound * (1 + 1e-9) + 50 * n * EPS * np.linalg.norm(A)
    cuts = [(s.cut_norm, s.cut_before) for s in steps if s.cut and s.cut_before is not None]
    assert cuts and any(o < 0.5 * d for d, o in cuts)
    assert sc.error_bound <= 3e-7 * np.sqrt(A.shape[1])


def test_a_cut_of_the_terms_before_the_block_is_all_in_the_columns_before(rng, monkeypatch):
    """Old terms cut by a rank cap beside stronger new ones: ``o_t = d_t``; new terms cut
    beside stronger old ones: ``o_t`` is their trace in the old columns, nearly 0."""
    import streamsvd.engine.update as update
    import streamsvd.engine.update_gram as update_gram

    steps = []
    core_step = update.core_step
    monkeypatch.setattr(update, "core_step",
                        lambda *a, **k: steps.append(core_step(*a, **k)) or steps[-1])
    monkeypatch.setattr(update_gram, "_path_applies", lambda *a: False)  # the exact path
    n = 200
    Q = np.linalg.qr(rng.standard_normal((n, 10)))[0]
    old = Q[:, :5] @ np.diag([1.0, 0.9, 0.8, 0.7, 0.6]) @ np.linalg.qr(
        rng.standard_normal((8, 5)))[0].T
    strong = 10 * Q[:, 5:] @ np.linalg.qr(rng.standard_normal((8, 5)))[0].T
    weak = 1e-3 * Q[:, 5:] @ np.linalg.qr(rng.standard_normal((8, 5)))[0].T
    for second, before in ((strong, 1.0), (weak, 0.0)):
        steps.clear()
        sc = ss.StreamCompressor(n, max_rank=5, oversampling=0, rule="jacobi", sweeps=None)
        sc.absorb(old)
        sc.absorb(second)
        step = steps[-1]
        assert step.cut == 5
        assert step.cut_before == pytest.approx(before * step.cut_norm, abs=1e-12)
