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
