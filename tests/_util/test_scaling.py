"""scale_into: exact power-of-two scaling of a block into float64, whatever its layout."""

import numpy as np
import pytest

from streamsvd._util.scaling import scale_into
from streamsvd.errors import NonFiniteError


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("order", ["F", "C"])
def test_the_scaled_copy_is_exact_and_its_peaks_in_half_one(rng, dtype, order):
    X = (rng.standard_normal((300, 7)) * np.logspace(-30, 30, 7)).astype(dtype)
    X[:, 3] = 0.0
    X = np.asarray(X, order=order)
    Y = np.empty(X.shape, order="F")
    exps, zero = scale_into(X, Y, name="X")
    np.testing.assert_array_equal(zero, np.arange(7) == 3)
    np.testing.assert_array_equal(Y, np.ldexp(X.astype(np.float64), -exps[np.newaxis, :]))
    peaks = np.max(np.abs(Y), axis=0)
    assert np.all((peaks[~zero] >= 0.5) & (peaks[~zero] < 1.0)) and exps[3] == 0


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_a_bad_entry_is_named_before_anything_is_written(dtype):
    X = np.asfortranarray(np.ones((5, 3), dtype=dtype))
    X[2, 1] = np.nan
    Y = np.zeros((5, 3), order="F")
    with pytest.raises(NonFiniteError, match="`X` must be finite"):
        scale_into(X, Y, name="X")
    assert not Y.any()


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("width", [1, 9])
def test_the_compiled_scaling_matches_ldexp_from_subnormal_to_extreme_columns(rng, dtype, width):
    # column-major blocks are scaled by the compiled kernel, which takes the peaks on the
    # entries' bit patterns; columns it declines (exponents beyond +-1000, float64
    # subnormals) send the whole block to the numpy form: both must give the same digits
    info = np.finfo(dtype)
    big = 990 if dtype == np.float64 else 100  # exponents the kernel takes
    beyond = 1010 if dtype == np.float64 else 120  # the float64 kernel declines it
    scales = [1.0, 0.0, -0.0, float(info.smallest_subnormal), float(info.tiny),
              float(info.max) / 4, 2.0**-60, 2.0**big, 2.0**-big, 2.0**beyond]
    for cols in ([0, 1, 2, 3, 4, 5, 6], [0, 1, 2, 6], [0, 7, 8], [0, 9]):
        if width == 1:
            cols = cols[-1:]
        X = np.empty((257, len(cols)), dtype=dtype, order="F")
        for k, c in enumerate(cols):
            with np.errstate(over="ignore", under="ignore"):
                X[:, k] = (rng.uniform(-1.0, 1.0, 257) * scales[c]).astype(dtype)
            X[rng.integers(257), k] = dtype(scales[c])  # the peak itself, exactly
        Y = np.full(X.shape, np.nan, order="F")
        exps, zero = scale_into(X, Y, name="X")
        Xw = X.astype(np.float64)
        np.testing.assert_array_equal(zero, ~np.any(Xw != 0, axis=0))
        np.testing.assert_array_equal(Y, np.ldexp(Xw, -exps[np.newaxis, :]))
        peaks = np.max(np.abs(Y), axis=0)
        assert np.all((peaks[~zero] >= 0.5) & (peaks[~zero] < 1.0))
        assert not np.any(exps[zero])


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("bad", [np.inf, -np.inf, np.nan])
def test_a_bad_entry_in_a_late_column_leaves_the_workspace_as_it_was(rng, dtype, bad):
    X = np.asfortranarray(rng.standard_normal((400, 6)).astype(dtype))
    X[399, 5] = bad
    Y = np.full(X.shape, 3.0, order="F")
    with pytest.raises(NonFiniteError, match="`X` must be finite"):
        scale_into(X, Y, name="X")
    assert np.all(Y == 3.0)
