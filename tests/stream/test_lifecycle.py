"""The SVD by default: oversampling while streaming, final sweeps at close and in the CLI."""

from __future__ import annotations

import io
import json
from contextlib import redirect_stdout

import numpy as np
import pytest

import streamsvd as ss
from streamsvd.cli import main
from streamsvd.errors import InputError
from streamsvd.parallel.cluster import TallCompressor, open_compressor
from streamsvd.store import open_store
from streamsvd.stream.options import CompressorOptions
from streamsvd.testing.matrices import with_spectrum

EPS = np.finfo(np.float64).eps


def _data(rng, n=90, m=120):
    return with_spectrum(np.logspace(0, -6, 60), n, m, rng)


def _absorb(sc, A, block=10):
    for j in range(0, A.shape[1], block):
        sc.absorb(A[:, j : j + block])
    return sc


def _assert_is_the_svd_of_itself(sc, k):
    """The amplitudes are the singular values of U V^T to LAPACK accuracy, k of them."""
    e = sc.expansion
    assert e.rank == k and sc.finalized
    s = np.linalg.svd(e.U @ e.V.T, compute_uv=False)[:k]
    np.testing.assert_allclose(e.amplitudes, s, rtol=0, atol=50 * k * EPS * s[0])
    W = e.V.T @ e.V
    assert np.max(np.abs(W - np.diag(np.diag(W)))) <= 50 * k * EPS * s[0] ** 2


def test_max_rank_oversamples_while_streaming_and_close_cuts_to_it(rng):
    A = _data(rng)
    k = 8
    sc = _absorb(ss.StreamCompressor(A.shape[0], max_rank=k), A)
    assert sc.oversampling == 10 and sc.streaming_rank == k + 10
    assert sc.rank == k + 10 and not sc.finalized
    streamed_bound = sc.error_bound
    sc.close()
    _assert_is_the_svd_of_itself(sc, k)
    assert sc.history[-1].kind == "finalize" and sc.error_bound >= streamed_bound
    err = np.linalg.norm(A - sc.expansion.to_dense())
    assert err <= sc.error_bound * (1 + 1e-9)
    # the oversampled stream ends closer to the optimum than a cap at every update
    capped = _absorb(ss.StreamCompressor(A.shape[0], max_rank=k, oversampling=0), A)
    assert capped.rank == k and all(h.rank <= k for h in capped.history)
    capped.close()
    s = np.linalg.svd(A, compute_uv=False)
    optimal = np.sqrt(np.sum(s[k:] ** 2))
    err_capped = np.linalg.norm(A - capped.expansion.to_dense())
    assert optimal <= err < err_capped
    sc.close()  # a second close does nothing
    assert [h.kind for h in sc.history].count("finalize") == 1


def test_close_commits_the_final_sweeps_once(rng, tmp_path):
    A = _data(rng)
    path = tmp_path / "b.zarr"
    with ss.StreamCompressor(A.shape[0], max_rank=6, store=path) as sc:
        _absorb(sc, A)
    with open_store(path, "r") as st:
        generation = st.generation
    with ss.StreamCompressor.open(path, mode="r") as back:
        _assert_is_the_svd_of_itself(back, 6)
        assert back.oversampling == 10
        np.testing.assert_array_equal(back.expansion.U, sc.expansion.U)
    with ss.StreamCompressor.open(path) as again:  # already final: closing commits nothing
        assert again.finalized
    with open_store(path, "r") as st:
        assert st.generation == generation


def test_close_without_final_sweeps_and_a_failing_block_keep_the_streamed_state(rng, tmp_path):
    A = _data(rng)
    path = tmp_path / "b.zarr"
    sc = _absorb(ss.StreamCompressor(A.shape[0], max_rank=6, store=path), A)
    sc.close(finalize=False)
    with ss.StreamCompressor.open(path, mode="r") as back:
        assert back.rank == 16 and not back.finalized
    with pytest.raises(RuntimeError, match="stop"):
        with ss.StreamCompressor.open(path) as sc:
            sc.absorb(A[:, :5])
            raise RuntimeError("stop")
    with ss.StreamCompressor.open(path, mode="r") as back:
        assert back.history[-1].kind == "absorb" and back.n_seen == A.shape[1] + 5


def test_tall_close_finalises_its_store(rng, tmp_path):
    A = _data(rng)
    ref = _absorb(ss.StreamCompressor(A.shape[0], max_rank=5), A)
    ref.close()
    tc = _absorb(TallCompressor(A.shape[0], chunk_rows=32, max_rank=5,
                                store=tmp_path / "t.zarr"), A)
    assert tc.rank == 15
    tc.close()
    with open_compressor(tmp_path / "t.zarr", mode="r") as back:
        assert back.finalized and back.rank == 5
        s0 = ref.amplitudes[0]
        np.testing.assert_allclose(back.amplitudes, ref.amplitudes, rtol=0,
                                   atol=100 * A.shape[0] * EPS * s0)


def test_oversampling_is_checked_and_old_stores_keep_their_cap():
    with pytest.raises(InputError, match="`oversampling` must be an integer >= 0; got int -1"):
        ss.StreamCompressor(5, max_rank=2, oversampling=-1)
    with pytest.raises(InputError, match="`oversampling` must be an integer >= 0"):
        ss.StreamCompressor(5, max_rank=2, oversampling=2.5)
    assert ss.StreamCompressor(5, oversampling=3).streaming_rank is None
    # a store of this layout written before the option existed truncated every update
    # (and one written before target errors existed has none)
    old = CompressorOptions.from_stored(5, {"max_rank": 4})
    assert (old.oversampling, old.max_rank, old.target_error, old.error_measure,
            old.streaming_share) == (0, 4, None, "relative", 0.9)
    assert CompressorOptions.from_stored(5, {"max_rank": 4, "oversampling": 7}).oversampling == 7


def _ingest(argv):
    out = io.StringIO()
    with redirect_stdout(out):
        status = main([str(a) for a in argv])
    return status, out.getvalue()


@pytest.mark.parametrize("mode", [[], ["--tall"], ["--scheduler", "threads"]])
def test_cli_ingest_ends_with_the_svd(rng, tmp_path, mode):
    A = _data(rng)
    np.save(tmp_path / "a.npy", A)
    store = tmp_path / "s.zarr"
    status, out = _ingest(["ingest", tmp_path / "a.npy", store, "--max-rank", 7,
                           "--block", 20, *mode])
    summary = json.loads(out)
    assert status == 0 and summary["finalized"] and summary["rank"] == 7
    assert summary["options"]["oversampling"] == 10
    with open_compressor(store, mode="r") as sc:
        _assert_is_the_svd_of_itself(sc, 7)
    status, out = _ingest(["info", store])
    assert "final sweeps  converged" in out and "oversampling 10" in out


def test_cli_final_sweeps_none_and_oversampling(rng, tmp_path, capsys):
    A = _data(rng)
    np.save(tmp_path / "a.npy", A)
    store = tmp_path / "s.zarr"
    status, out = _ingest(["ingest", tmp_path / "a.npy", store, "--max-rank", 7,
                           "--oversampling", 3, "--final-sweeps", "none", "--block", 20])
    summary = json.loads(out)
    assert status == 0 and not summary["finalized"] and summary["rank"] == 10
    status, out = _ingest(["info", store])
    assert "final sweeps  not run" in out
    # resuming with the default final sweeps converges it; a differing option is refused
    assert main(["ingest", str(tmp_path / "a.npy"), str(store), "--resume",
                 "--oversampling", "4"]) == 2
    assert "--oversampling 4 (STORE has 3)" in capsys.readouterr().err
    status, out = _ingest(["ingest", tmp_path / "a.npy", store, "--resume"])
    assert status == 0 and json.loads(out)["finalized"] and json.loads(out)["rank"] == 7
    assert main(["ingest", str(tmp_path / "a.npy"), str(tmp_path / "t.zarr"),
                 "--oversampling", "3"]) == 2
    assert "--oversampling adds terms to --max-rank" in capsys.readouterr().err
    assert not (tmp_path / "t.zarr").exists()
    assert main(["ingest", str(tmp_path / "a.npy"), str(tmp_path / "t.zarr"),
                 "--max-rank", "2", "--oversampling", "-1"]) == 2
    assert "--oversampling: must be an integer >= 0; got '-1'" in capsys.readouterr().err


def test_a_cut_by_the_rank_cap_is_made_on_the_converged_core(rng):
    """A rank-8 signal in noise 100x below it: cutting by the cap on the converged core
    keeps the signal, so the streamed basis is optimal but for the noise's coupling;
    thresholds alone keep the paper's one sweep per update."""
    k = 8
    s = np.r_[np.logspace(0, -1, k), np.logspace(-3, -6, 112)]
    A = with_spectrum(s, 300, 120, rng)
    optimal = np.sqrt(np.sum(s[k:] ** 2))
    for oversampling, excess in ((0, 1e-5), (10, 1e-6)):
        sc = _absorb(ss.StreamCompressor(300, max_rank=k, oversampling=oversampling), A, 30)
        # the cap binds at every update: the core is converged, by Jacobi sweeps or by
        # the eigenvalues of the snapshots' Gram (no sweep, two passes)
        assert all(h.sweeps > 1 or (h.sweeps, h.passes) == (0, 2) for h in sc.history)
        sc.finalize()
        assert np.linalg.norm(A - sc.expansion.to_dense()) <= (1 + excess) * optimal
    sc = _absorb(ss.StreamCompressor(300, rtol=1e-4), A, 30)
    assert [h.sweeps for h in sc.history] == [1, 1, 1, 1]
