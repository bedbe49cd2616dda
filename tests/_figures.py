"""Check that a saved figure was drawn: not blank, not a filled square, in colour."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def assert_drawn(path: Path, *, min_ink: float = 0.01, max_ink: float = 0.6) -> np.ndarray:
    """Assert that the PNG at ``path`` holds a drawing; return its pixels.

    The share of non-white pixels must lie between ``min_ink`` and ``max_ink`` (axes,
    labels and curves, not a blank or black image), and the image must hold more than
    two colours (curves drawn, not only black text on white).
    """
    import matplotlib.image

    assert path.is_file(), f"{path} was not written"
    image = matplotlib.image.imread(path)[..., :3]
    ink = (image < 0.9).any(axis=-1).mean()
    assert min_ink < ink < max_ink, f"{path}: {ink:.3f} of the pixels are drawn"
    colours = np.unique((image.reshape(-1, 3) * 15).round(), axis=0)
    assert len(colours) > 2, f"{path}: only {len(colours)} colours"
    return image
