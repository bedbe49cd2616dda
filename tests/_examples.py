"""The example counts of the property tests that set their own.

A property test that sets ``max_examples`` (its cost per example) overrides the profile's
count; it passes its count through :func:`examples`, so that the ``thorough`` profile
(``HYPOTHESIS_PROFILE=thorough``, a long search by hand) multiplies it instead. A search
of 30,000 examples of one such test found a right factor 73 times the test's rounding
slack from its data, which 40 examples had not.
"""

import os

THOROUGH_FACTOR = 25


def examples(count: int) -> int:
    """Return ``count``, or ``THOROUGH_FACTOR`` times it under the ``thorough`` profile."""
    if os.environ.get("HYPOTHESIS_PROFILE") == "thorough":
        return THOROUGH_FACTOR * count
    return count
