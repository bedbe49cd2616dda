"""Data at the ends of the float64 range: results that are representable are computed,
the others refused by name with nothing changed."""

import hashlib
import math

import numpy as np
import pytest

import streamsvd as ss
from streamsvd.errors import FloatRangeError, InputError
from streamsvd.parallel.cluster import tall_compress, tree_compress

EPS = np.finfo(float).eps
N = 30
OPTIONS = [{}, {"target_error": 1e-3}, {"target_error": 1e-3, "error_measure": "mean_l2"},
           {"max_rank": 2}]
HALF, TWICE = {"inner": np.full(N, 0.5)}, {"inner": np.full(N, 2.0)}  # norms 0.71, 1.41


def _fingerprint(sc):
    E = sc.expansion
    return hashlib.sha1(np.asarray(E.U).tobytes() + np.asarray(E.V).tobytes()
                        + repr((sc.error_bound, sc.n_seen, len(sc.history))).encode()
                        ).hexdigest()


@pytest.mark.parametrize("options", [*OPTIONS, HALF])
def test_collinear_snapshots_near_1e308_give_their_expansion(options):
    """Three copies of a column of norm 1e308: the singular value sqrt(3) 1e308 is
    representable, and so is every right vector's entry (1e308). LAPACK's Householder QR
    of the core overflowed there (alpha - beta > 2^1024), and the right vectors were NaN."""
    x = np.full((N, 1), 1e308 / math.sqrt(N))
    sc = ss.StreamCompressor(N, **options)
    for _ in range(3):
        sc.absorb(x)
    E = sc.expansion
    w = options.get("inner", np.ones(N))
    assert E.U.shape[1] == 1
    assert np.all(np.isfinite(E.V))
    scale = math.sqrt(float(w[0]))  # ||x||_M = 1e308 sqrt(w)
    np.testing.assert_allclose(np.abs(E.V[:, 0]), 1e308 * scale, rtol=50 * EPS)
    np.testing.assert_allclose(np.abs(E.U[:, 0]) * math.sqrt(N) * scale, 1.0, rtol=50 * EPS)
    assert sc.error_bound <= 50 * 3 * N * EPS * 1e308 * math.sqrt(3)


def _beyond(kind, options, tmp_path):
    """Run ``kind`` so that the expansion's norm would pass 1.8e308; return the call."""
    x = np.full((N, 1), 1e308 / math.sqrt(N))
    if kind == "tall":
        return lambda: tall_compress(np.repeat(x, 4, axis=1), block=1, chunk_rows=8,
                                     **options)
    if kind == "tree":
        return lambda: tree_compress(np.repeat(x, 4, axis=1), block=1, leaf_columns=1,
                                     **options)
    sc = ss.StreamCompressor(N, store=tmp_path / "s.zarr", **options)
    for _ in range(3 if "inner" not in options else 1):
        sc.absorb(x)
    if kind == "absorb":
        return sc, lambda: sc.absorb(x)
    if kind == "merge":
        other = ss.StreamCompressor(N, **options)
        other.absorb(x)
        return sc, lambda: sc.merge(other)
    return sc, lambda: sc.add(x, np.ones((sc.n_seen, 1)))


@pytest.mark.parametrize("options", [*OPTIONS, TWICE])
@pytest.mark.parametrize("kind, argument", [
    ("absorb", "`columns`"), ("merge", "`other`"), ("add", "the increment (`U_k`"),
])
def test_an_update_beyond_the_range_is_refused_and_changes_nothing(tmp_path, kind, argument,
                                                                   options):
    sc, update = _beyond(kind, options, tmp_path)
    before = _fingerprint(sc)
    with pytest.raises(FloatRangeError, match=r"would take the expansion beyond the "
                       r"float64 range") as info:
        update()
    assert str(info.value).startswith(argument)
    assert isinstance(info.value, InputError) and isinstance(info.value, OverflowError)
    assert _fingerprint(sc) == before
    sc.flush()
    sc.close(finalize=False)
    reopened = ss.StreamCompressor.open(tmp_path / "s.zarr", mode="r")
    assert _fingerprint(reopened) == before
    reopened.close()


@pytest.mark.parametrize("kind", ["tall", "tree"])
def test_the_parallel_modes_name_their_source(tmp_path, kind):
    with pytest.raises(FloatRangeError, match=r"^`source`.*beyond the float64 range"):
        _beyond(kind, {}, tmp_path)()


def test_an_absolute_target_far_above_data_near_1e_minus_181():
    """Data at 2^-600 under a ``mean_l2`` target of 1e-4 (every term cut): the budget a
    block may set aside, 2^1200 times the target's energy in the block's scaled units,
    raised ``OverflowError: math range error``; nothing is set aside there now, and the
    target's cut removes every term."""
    n, m = 200, 150
    x = np.linspace(0, 1, n)[:, np.newaxis]
    t = np.linspace(0, 1, m)[np.newaxis, :]
    A = np.ldexp(np.exp(-((x - 0.2 - 0.6 * t) / (0.05 + 0.05 * t)) ** 2), -600)
    sc = ss.StreamCompressor(n, target_error=1e-4, error_measure="mean_l2")
    for j in range(0, m, 10):
        sc.absorb(A[:, j:j + 10])
    assert sc.rank == 0
    assert sc.target_met
    # everything cut: the bound covers the data (scaled back, no underflow)
    norm = np.ldexp(np.linalg.norm(np.ldexp(A, 600)), -600)
    assert norm <= sc.error_bound * (1 + 1e-12)


@pytest.mark.parametrize("exponent", [-1050, -1060, -1070])
@pytest.mark.parametrize("options", [{}, {"target_error": 1e-3}, {"max_rank": 3},
                                     {"inner": np.linspace(0.1, 10.0, 40)}])
@pytest.mark.parametrize("block", [1, 5])
def test_subnormal_data_within_the_bound_and_the_subnormal_spacing(exponent, options, block):
    """Data at 2^-1050 .. 2^-1070 (1e-316 .. 1e-322, subnormal): the amplitudes and
    the right vectors' entries round to the spacing of the subnormal numbers, 2^-1074,
    not to eps. ``||dV||_F <= (k + 1) sqrt(m) 2^-1074`` for k terms (the core's rounding
    carried by the orthonormal rows, and the product's own); twice that is allowed
    beside the LAPACK-style allowance. Measured: up to 0.91 of the single allowance over
    40 random pulses, 5 exponents and 6 option sets; at 2^-1060 the error is 2.7e-3 of
    the data's norm where the bound is 0."""
    n, m = 40, 30
    x = np.linspace(0, 1, n)[:, np.newaxis]
    t = np.linspace(0, 1, m)[np.newaxis, :]
    P = np.exp(-((x - 0.2 - 0.6 * t) / 0.1) ** 2)
    A = np.ldexp(P, exponent)
    sc = ss.StreamCompressor(n, **options)
    for j in range(0, m, block):
        sc.absorb(A[:, j:j + block])
    sc.finalize()
    E = sc.expansion
    k = E.U.shape[1]
    w = np.asarray(options.get("inner", np.ones(n)))[:, np.newaxis]
    # measured 2^-exponent times larger, exactly (no subnormal left in the check)
    err = np.linalg.norm(np.sqrt(w) * np.ldexp(A - E.U @ E.V.T, -exponent))
    allowance = (np.ldexp(sc.error_bound, -exponent)
                 + 50 * max(n, m) * EPS * np.linalg.norm(np.sqrt(w) * np.ldexp(A, -exponent))
                 + 2 * (k + 1) * math.sqrt(m * w.max()) * 2.0 ** (-1074 - exponent))
    assert err <= allowance
    assert np.linalg.norm(E.U.T @ (w * E.U) - np.eye(k)) <= 10 * n * EPS
