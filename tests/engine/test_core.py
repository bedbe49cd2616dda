"""A target error in: the fewest terms whose guaranteed bound meets it."""

import json
import logging
import math

import numpy as np
import pytest
import scipy.linalg

import streamsvd as ss
from streamsvd.cli import main
from streamsvd.engine.core import _singular_values
from streamsvd.testing import with_spectrum

EPS = np.finfo(float).eps


def _optimal_rank(s, budget):
    """The fewest leading singular values whose tail energy is within ``budget``."""
    tail = np.sqrt(np.append(np.cumsum((s**2)[::-1])[::-1], 0.0))
    return int(np.argmax(tail <= budget))


@pytest.fixture
def matrix(rng):
    return with_spectrum(np.logspace(0, -8, 150), 300, 240, rng)


@pytest.mark.parametrize("target", [1e-2, 1e-4, 1e-6])
def test_relative_target_keeps_near_optimal_modes_with_a_sharp_bound(matrix, target):
    A = matrix
    norm_A = np.linalg.norm(A)
    s = np.linalg.svd(A, compute_uv=False)
    sc = ss.StreamCompressor(A.shape[0], target_error=target, rule="jacobi", sweeps=None)
    for j in range(0, A.shape[1], 30):
        sc.absorb(A[:, j : j + 30])
        err = np.linalg.norm(A[:, : j + 30] - sc.expansion.to_dense())
        assert err <= sc.error_bound * (1 + 1e-9) + 50 * A.shape[0] * EPS * norm_A
        share = sc.streaming_share
        assert sc.error_bound <= share * target * norm_A * (1 + 1e-12)  # the streaming share
    sc.finalize()
    err = np.linalg.norm(A - sc.expansion.to_dense())
    assert err <= target * norm_A
    assert sc.target_met and sc.error_in_measure <= target
    assert err <= sc.error_bound * (1 + 1e-9) + 50 * A.shape[0] * EPS * norm_A
    assert sc.error_bound <= 1.5 * err
    assert sc.rank <= _optimal_rank(s, target * norm_A) + 2


def test_mean_l2_target_in_an_inner_product(rng):
    n, m = 200, 160
    w = rng.uniform(0.5, 2.0, n)
    A = with_spectrum(np.logspace(0, -6, 100), n, m, rng)
    target = 1e-4
    sc = ss.StreamCompressor(n, inner=w, target_error=target, error_measure="mean_l2",
                             rule="jacobi", sweeps=None)
    for j in range(0, m, 20):
        sc.absorb(A[:, j : j + 20])
    sc.finalize()
    E = A - sc.expansion.to_dense()
    mean_l2 = np.sqrt(np.sum(w[:, None] * E**2) / m)
    assert mean_l2 <= target
    assert sc.target_met and sc.error_in_measure <= target
    assert np.sqrt(np.sum(w[:, None] * E**2)) <= sc.error_bound * (1 + 1e-9)
    # the optimum in the inner product: the SVD of W^(1/2) A
    s = np.linalg.svd(np.sqrt(w)[:, None] * A, compute_uv=False)
    assert sc.rank <= _optimal_rank(s, target * np.sqrt(m)) + 1


def test_absolute_target_and_the_stream_needs_no_length(matrix):
    A = matrix
    target = 1e-3
    sc = ss.StreamCompressor(A.shape[0], target_error=target, error_measure="absolute")
    for j in range(0, A.shape[1], 40):
        sc.absorb(A[:, j : j + 40])
    sc.finalize()
    assert np.linalg.norm(A - sc.expansion.to_dense()) <= target
    assert sc.target_met


def test_a_rank_cap_that_breaks_the_target_says_so(matrix, caplog):
    sc = ss.StreamCompressor(matrix.shape[0], target_error=1e-8, max_rank=5)
    sc.absorb(matrix)
    with caplog.at_level(logging.WARNING, logger="streamsvd"):
        sc.finalize()
    assert sc.target_met is False
    assert "not met" in caplog.text and "max_rank=5" in caplog.text
    assert ss.StreamCompressor(10).target_met is None


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"target_error": 0.0}, r"`target_error` must be > 0"),
        ({"target_error": -1.0}, r"`target_error` must be a finite number >= 0"),
        ({"target_error": float("nan")}, r"`target_error` must be a finite number"),
        ({"target_error": 1e-3, "eps": 1e-6}, r"`target_error` and `eps` cannot be combined"),
        ({"target_error": 1e-3, "rtol": 1e-6}, r"`target_error` and `rtol` cannot be combined"),
        ({"target_error": 1e-3, "error_measure": "l2"}, r"`error_measure` must be one of"),
        ({"target_error": 1e-3, "streaming_share": 0.0}, r"`streaming_share` must be"),
        ({"target_error": 1e-3, "streaming_share": 1.5}, r"`streaming_share` must be"),
    ],
)
def test_bad_target_options_name_the_argument(kwargs, match):
    with pytest.raises(ss.InputError, match=match):
        ss.StreamCompressor(10, **kwargs)


def test_target_is_stored_and_resumed(tmp_path, matrix):
    A = matrix
    path = tmp_path / "s.zarr"
    sc = ss.StreamCompressor(A.shape[0], target_error=1e-3, error_measure="mean_l2",
                             streaming_share=0.8, store=path)
    sc.absorb(A[:, :100])
    sc.close(finalize=False)
    with ss.StreamCompressor.open(path) as again:
        assert (again.target_error, again.error_measure, again.streaming_share) == (
            1e-3, "mean_l2", 0.8)
        again.absorb(A[:, 100:])
    with ss.StreamCompressor.open(path, mode="r") as done:
        assert done.target_met
        E = A - done.expansion.to_dense()
        assert np.sqrt(np.sum(E**2) / A.shape[1]) <= 1e-3


def test_cli_target_error_and_info(tmp_path, matrix, capsys):
    src = tmp_path / "a.npy"
    np.save(src, matrix)
    store = tmp_path / "s.zarr"
    assert main(["ingest", str(src), str(store), "--target-error", "1e-4", "--block", "40",
                 "--rule", "jacobi", "--sweeps", "converge"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["target_met"] is True and summary["error_in_measure"] <= 1e-4
    assert summary["options"]["target_error"] == 1e-4
    assert main(["info", str(store)]) == 0
    assert "target error  1.000e-04 (relative)" in capsys.readouterr().out
    assert main(["ingest", str(src), str(tmp_path / "t.zarr"), "--target-error", "1e-4",
                 "--eps", "1e-3"]) == 2
    assert "--eps: not allowed with argument --target-error" in capsys.readouterr().err
    assert main(["ingest", str(src), str(tmp_path / "u.zarr"), "--streaming-share",
                 "0.5"]) == 2
    assert "--streaming-share splits the budget of --target-error" in capsys.readouterr().err
    assert main(["ingest", str(src), str(tmp_path / "v.zarr"), "--threads", "2",
                 "--scheduler", "threads"]) == 2
    assert "--threads applies to the in-memory mode" in capsys.readouterr().err


@pytest.mark.parametrize("target", [1e-2, 1e-4])
def test_tree_spends_its_leaves_budget_once_and_keeps_the_streams_modes(target):
    """The tree's merges cut nothing for the target (only rounding noise, below the
    rejection threshold ``n eps`` of the largest amplitude); its leaves spend the
    streaming share and the root's finalize the rest, as pyMOR's dist_vectorarray_hapod:
    the tree keeps the modes of the stream (within one) and its bound holds."""
    from streamsvd.parallel.cluster import tree_compress

    x = np.linspace(0.0, 1.0, 400)[:, np.newaxis]
    t = np.linspace(0.0, 1.0, 320)[np.newaxis, :]
    A = np.exp(-((x - 0.2 - 0.6 * t) / (0.05 + 0.05 * t)) ** 2)
    kw = dict(target_error=target, error_measure="mean_l2", rule="jacobi", sweeps=None)
    sc = ss.StreamCompressor(400, **kw)
    for j in range(0, 320, 40):
        sc.absorb(A[:, j : j + 40])
    sc.finalize()
    tree = tree_compress(A, block=40, leaf_columns=40, **kw)
    noise = 400 * np.finfo(float).eps * np.linalg.norm(A, 2)
    merges = [r for r in tree.history if r.kind == "merge"]
    assert merges and all(r.discarded <= math.sqrt(r.cut + r.rejected) * noise for r in merges)
    tree.finalize()
    err = np.linalg.norm(A - tree.expansion.to_dense()) / np.sqrt(320)
    assert err <= tree.error_in_measure * (1 + 1e-9) <= target * (1 + 1e-12)
    assert tree.rank <= sc.rank + 1


@pytest.mark.parametrize("shape", [(20, 10), (10, 20), (3, 2), (28, 5), (2, 2)])
def test_the_couplings_singular_values_are_svdvals_digits(shape):
    rng = np.random.default_rng(sum(shape))
    for scale in (1e-200, 1e-8, 1.0, 1e150):
        W = rng.standard_normal(shape) * scale
        np.testing.assert_array_equal(_singular_values(W), scipy.linalg.svdvals(W))
