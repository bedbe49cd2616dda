"""check_finite: a finite sum decides at once; an overflow or a bad entry is looked at."""

import numpy as np
import pytest

from streamsvd._util.validation import check_finite
from streamsvd.errors import NonFiniteError


def test_finite_entries_whose_sum_overflows_pass():
    check_finite(np.full((3, 4), 1e308), "X")  # the sum is inf, every entry finite


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("big", [1.0, 1e308])
def test_a_bad_entry_is_named(bad, big):
    X = np.full((3, 4), big)
    X[2, 1] = bad
    with pytest.raises(NonFiniteError, match=r"`X` must be finite; got 1 .* index \(2, 1\)"):
        check_finite(X, "X")


def test_opposite_infinities_are_found():
    X = np.zeros(5)
    X[1], X[3] = np.inf, -np.inf  # their sum is NaN
    with pytest.raises(NonFiniteError, match="got 2 NaN or infinite entries"):
        check_finite(X, "X")
