"""The ``--products`` rows of ``tight_targets.py``: the flops of an update, counted.

Each contender runs once more, untimed, with its ``n``-sized dense products wrapped and
counted (a product of an ``n x a`` by an ``a x b`` matrix is ``2 n a b`` flops), and the
columns its sparse ``M`` multiplies counted. Unlike CPU time, the counts do not move with
the machine's load: they say whether a ratio near 1 is the products' or the rest's.

* streamsvd: the block Grams (:func:`streamsvd.algebra.blas.gram`, wherever it is
  called from; the residual's joint product with the basis among them), the
  projections on the basis and their subtraction, the compactions and the Grams of
  written columns, the products of ``_mm`` (the directions the rounds and the sketch
  form), the sketch's coefficients, the triangular solves of CholeskyQR and the rounds
  (``n b^2``), the basis's linear combinations, the staged Gram path's products and
  the kept directions ``Z W_k`` (:func:`streamsvd.linalg.extend._split_on_kept`). Left
  out: the maps of the few directions the column rule rejects (``n s r`` with
  ``r < s``, a few per update) and everything on the small cores.
* HAPOD: pyMOR's ``inner``, ``lincomb`` and ``axpy`` of its NumPy vector arrays (the
  method of snapshots' Gram, its modes, and Gram-Schmidt when ``pod`` re-orthonormalises)
  and the columns ``NumpyMatrixOperator.apply`` multiplies.

The wrappers are put in place for one run and removed after it.
"""

from __future__ import annotations

import contextlib
import sys
from collections import Counter
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np

__all__ = ["hapod_products", "streamsvd_products"]


@contextlib.contextmanager
def _wrapped(patches: list[tuple[Any, str, Callable[..., Any]]]) -> Iterator[None]:
    """Set each ``(owner, name, wrapper)`` for the block, then restore the originals."""
    saved = [(owner, name, getattr(owner, name)) for owner, name, _ in patches]
    try:
        for owner, name, wrapper in patches:
            setattr(owner, name, wrapper)
        yield
    finally:
        for owner, name, original in reversed(saved):
            setattr(owner, name, original)


def _everywhere(function: Callable[..., Any], wrapper: Callable[..., Any]
                ) -> list[tuple[Any, str, Callable[..., Any]]]:
    """The patches that replace ``function`` in every streamsvd module that imported it."""
    return [(module, name, wrapper)
            for module in list(sys.modules.values())
            if getattr(module, "__name__", "").startswith("streamsvd")
            for name, value in list(vars(module).items()) if value is function]


def streamsvd_products(run: Callable[[], Any], updates: int) -> dict[str, float]:
    """Run ``run()`` with streamsvd's products counted; return them per update.

    Returns Mflop per update by kind, their ``total`` and ``m_columns`` (the columns
    ``M`` was applied to, per update).
    """
    import streamsvd.algebra.blas as blas
    import streamsvd.algebra.inner as inner
    import streamsvd.algebra.memory as memory
    import streamsvd.linalg.blocks as blocks
    import streamsvd.linalg.extend as extend
    import streamsvd.linalg.sketch as sketch

    flops: Counter[str] = Counter()
    columns: Counter[str] = Counter()
    gram, subtract, mm = blas.gram, blas.subtract_product, blocks._mm
    solve, dgemm = blocks.right_solve, sketch.dgemm
    basis = memory.MemoryBasis
    originals = {name: getattr(basis, name) for name in (
        "project", "residual_products", "_compact", "_gram_of", "lincomb",
        "products_beside")}
    apply, split_on_kept, kept_clean = inner.MatrixInner._apply, extend._split_on_kept, \
        extend.kept_clean
    shape: list[tuple[int, int]] = []  # the residual's (n, b) while _split_on_kept runs

    def counted_gram(X: np.ndarray, product: Any, MX: np.ndarray | None = None) -> Any:
        flops["gram"] += 2 * X.shape[0] * X.shape[1] ** 2
        return gram(X, product, MX)

    def counted_subtract(X: np.ndarray, A: np.ndarray, K: np.ndarray) -> None:
        flops["subtract"] += 2 * X.shape[0] * A.shape[1] * X.shape[1]
        subtract(X, A, K)

    def counted_mm(A: np.ndarray, B: np.ndarray) -> np.ndarray:
        flops["maps"] += 2 * A.shape[0] * A.shape[1] * B.shape[1]
        return mm(A, B)

    def counted_solve(A: np.ndarray, L: np.ndarray) -> np.ndarray:
        flops["solve"] += A.shape[0] * A.shape[1] ** 2
        return solve(A, L)

    def counted_dgemm(alpha: float, a: np.ndarray, b: np.ndarray, **kw: Any) -> Any:
        # the sketch's coefficients (M Q)^T Z
        flops["project"] += 2 * a.shape[0] * a.shape[1] * b.shape[1]
        return dgemm(alpha, a, b, **kw)

    def project(self: Any, X: np.ndarray, G: Any) -> Any:
        flops["project"] += 2 * X.shape[0] * self.width * X.shape[1]
        return originals["project"](self, X, G)

    def residual_products(self: Any, Z: np.ndarray, MZ: np.ndarray) -> Any:
        before = sum(flops.values())
        out = originals["residual_products"](self, Z, MZ)
        if sum(flops.values()) == before:  # one joint product [MQ, MZ]^T Z, not apart
            flops["gram"] += 2 * Z.shape[0] * (self.width + Z.shape[1]) * Z.shape[1]
        return out

    def compact(self: Any, G: np.ndarray, parts: Any, **kw: Any) -> Any:
        twice = 1 if self.inner.is_euclidean else 2  # Q G, and M Q G beside it
        flops["compact"] += 2 * self.n * G.shape[0] * G.shape[1] * twice
        return originals["_compact"](self, G, parts, **kw)

    def gram_of(self: Any, Q: np.ndarray, MQ: np.ndarray) -> Any:
        flops["gram"] += 2 * Q.shape[0] * Q.shape[1] ** 2
        return originals["_gram_of"](self, Q, MQ)

    def lincomb(self: Any, G: np.ndarray) -> Any:
        flops["maps"] += 2 * self.n * G.shape[0] * G.shape[1]
        return originals["lincomb"](self, G)

    def products_beside(self: Any, X: np.ndarray) -> Any:
        flops["gram"] += 2 * X.shape[0] * (self.width + X.shape[1]) * X.shape[1]
        return originals["products_beside"](self, X)

    def counted_apply(self: Any, X: np.ndarray, out: Any, dots: Any) -> Any:
        columns["M"] += X.shape[1] if X.ndim == 2 else 1
        return apply(self, X, out, dots)

    def counted_split(basis_: Any, G: Any, Z: np.ndarray, *args: Any) -> Any:
        shape.append(Z.shape)
        try:
            return split_on_kept(basis_, G, Z, *args)
        finally:
            shape.pop()

    def counted_clean(along: np.ndarray, *args: Any) -> bool:
        if shape:  # Z W_k was formed to measure it along the basis
            n, b = shape[-1]
            flops["maps"] += 2 * n * b * along.shape[1]
        return kept_clean(along, *args)

    patches = [
        *_everywhere(gram, counted_gram), *_everywhere(subtract, counted_subtract),
        *_everywhere(mm, counted_mm), *_everywhere(solve, counted_solve),
        (sketch, "dgemm", counted_dgemm),
        (basis, "project", project), (basis, "residual_products", residual_products),
        (basis, "_compact", compact), (basis, "_gram_of", gram_of),
        (basis, "lincomb", lincomb), (basis, "products_beside", products_beside),
        (inner.MatrixInner, "_apply", counted_apply),
        (extend, "_split_on_kept", counted_split), (extend, "kept_clean", counted_clean),
    ]
    with _wrapped(patches):
        run()
    return _per_update(flops, columns["M"], updates)


def hapod_products(run: Callable[[], Any], updates: int) -> dict[str, float]:
    """Run ``run()`` with pyMOR's products counted; return them per update (as above)."""
    from pymor.operators.numpy import NumpyMatrixOperator
    from pymor.vectorarrays.numpy import NumpyVectorArrayImpl as Impl

    flops: Counter[str] = Counter()
    columns: Counter[str] = Counter()
    inner, lincomb, axpy = Impl.inner, Impl.lincomb, Impl.axpy
    apply = NumpyMatrixOperator.apply

    # pyMOR's NumPy arrays hold one vector per column (dim x len)
    def counted_inner(self: Any, other: Any, ind: Any, oind: Any) -> Any:
        out = inner(self, other, ind, oind)
        flops["gram"] += 2 * self._array.shape[0] * out.size
        return out

    def counted_lincomb(self: Any, coefficients: np.ndarray, ind: Any) -> Any:
        flops["maps"] += 2 * self._array.shape[0] * coefficients.size
        return lincomb(self, coefficients, ind)

    def counted_axpy(self: Any, alpha: Any, x: Any, ind: Any, xind: Any) -> Any:
        flops["subtract"] += 2 * self._array.shape[0] * max(np.size(alpha), 1)
        return axpy(self, alpha, x, ind, xind)

    def counted_apply(self: Any, U: Any, mu: Any = None) -> Any:
        columns["M"] += len(U)
        return apply(self, U, mu=mu)

    with _wrapped([(Impl, "inner", counted_inner), (Impl, "lincomb", counted_lincomb),
                   (Impl, "axpy", counted_axpy),
                   (NumpyMatrixOperator, "apply", counted_apply)]):
        run()
    return _per_update(flops, columns["M"], updates)


def _per_update(flops: Counter[str], m_columns: int, updates: int) -> dict[str, float]:
    """Mflop per update by kind, their total, and the columns ``M`` multiplied per update."""
    out = {kind: value / updates / 1e6 for kind, value in sorted(flops.items())}
    out["total"] = sum(flops.values()) / updates / 1e6
    out["m_columns"] = m_columns / updates
    return out
