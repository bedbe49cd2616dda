"""Structured quadrangle meshes of the billet and of a rectangular block.

Nodes are numbered row by row (``node = j * (nx + 1) + i`` for column ``i`` and row
``j``); quadrangles are listed counter-clockwise. Coordinates are ``(x, y)`` in the plane
or ``(r, z)`` for an axisymmetric body (``r`` the distance to the axis).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .errors import ProblemError

__all__ = ["Mesh", "mapped_grid", "rectangle"]


@dataclass(frozen=True, eq=False)
class Mesh:
    """A quadrangle mesh.

    Parameters
    ----------
    coords : ndarray, shape (n_nodes, 2)
        Node coordinates.
    quads : ndarray of int, shape (n_elements, 4)
        Node indices of each quadrangle, counter-clockwise.
    shape : tuple of int
        ``(nx, ny)``: number of element columns and rows of the structured grid.
    """

    coords: np.ndarray
    quads: np.ndarray
    shape: tuple[int, int]

    @property
    def n_nodes(self) -> int:
        """Number of nodes."""
        return int(self.coords.shape[0])

    def node(self, i: int | np.ndarray, j: int | np.ndarray) -> np.ndarray:
        """Return the index of the node in column ``i`` and row ``j``."""
        return np.asarray(j) * (self.shape[0] + 1) + np.asarray(i)

    def column(self, i: int) -> np.ndarray:
        """Return the nodes of column ``i`` from bottom to top."""
        return np.asarray(self.node(i, np.arange(self.shape[1] + 1)), dtype=np.intp)

    def row(self, j: int) -> np.ndarray:
        """Return the nodes of row ``j`` from left to right."""
        return np.asarray(self.node(np.arange(self.shape[0] + 1), j), dtype=np.intp)


def mapped_grid(
    nx: int, ny: int, height: float, right: Callable[[np.ndarray], np.ndarray]
) -> Mesh:
    """Return a structured grid of ``{0 <= x <= right(y), 0 <= y <= height}``.

    Parameters
    ----------
    nx, ny : int
        Number of element columns and rows.
    height : float
        Height of the body.
    right : callable
        ``right(y)``, the abscissa of the right side at height ``y`` (vectorised).

    Returns
    -------
    Mesh
        Row ``j`` lies at ``y = j * height / ny``; node ``i`` of a row at
        ``x = i / nx * right(y)``.
    """
    if nx < 1 or ny < 1:
        raise ProblemError(f"`nx` and `ny` must be at least 1; got nx={nx}, ny={ny}.")
    y = np.linspace(0.0, height, ny + 1)
    xi = np.linspace(0.0, 1.0, nx + 1)
    X = xi[None, :] * np.asarray(right(y), dtype=float)[:, None]
    Y = np.broadcast_to(y[:, None], X.shape)
    coords = np.column_stack([X.ravel(), Y.ravel()])
    i, j = np.meshgrid(np.arange(nx), np.arange(ny))
    n0 = (j * (nx + 1) + i).ravel()
    quads = np.column_stack([n0, n0 + 1, n0 + nx + 2, n0 + nx + 1]).astype(np.intp)
    return Mesh(coords, quads, (nx, ny))


def rectangle(nx: int, ny: int, width: float, height: float) -> Mesh:
    """Return a structured grid of the rectangle ``[0, width] x [0, height]``."""
    return mapped_grid(nx, ny, height, lambda y: np.full_like(y, width))
