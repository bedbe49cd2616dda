"""What an update of the stream is given: its operand, and the options of its step.

:func:`_merge_operand` checks what :meth:`StreamCompressor.merge
<streamsvd.stream.compressor.StreamCompressor.merge>` is given and returns it as a
:class:`_MergeOperand` (basis, coordinates, core, right factor, bound);
:func:`_increment` checks the arguments of :meth:`StreamCompressor.add
<streamsvd.stream.compressor.StreamCompressor.add>`; :func:`_merge_options` and
:func:`_final_options` are the step options of a merge and of :meth:`StreamCompressor.finalize
<streamsvd.stream.compressor.StreamCompressor.finalize>`.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Any, cast

import numpy as np
import scipy.linalg.blas as blas

from streamsvd._util.validation import as_float_array, check_choice, check_positive_int
from streamsvd.algebra.inner import InnerProduct, check_same_inner
from streamsvd.algebra.memory import MemoryBasis
from streamsvd.algebra.panels.basis import PanelBasis
from streamsvd.algebra.panels.lazy import LazyBlock
from streamsvd.engine.bound import Bound
from streamsvd.engine.core import r_factor
from streamsvd.errors import InputError
from streamsvd.linalg.expansion import Expansion
from streamsvd.linalg.rotations import RULES
from streamsvd.stream.lifecycle import Lifecycle

if TYPE_CHECKING:
    from streamsvd.engine import StepOptions
    from streamsvd.engine.state import State
    from streamsvd.stream.options import CompressorOptions

__all__: list[str] = []


@dataclasses.dataclass(frozen=True)
class _MergeOperand:
    """What :meth:`StreamCompressor.merge` absorbs: ``U_o V_o^T`` with ``U_o = Q Z``.

    ``Q`` is the other expansion's basis, ``Z`` its coordinates (None when ``Q`` holds the
    left vectors themselves), ``R`` the core (``V_o = Y R``), ``Y`` the orthonormal right
    factor (None when the right vectors are not kept), ``m`` the number of snapshots and
    ``bound`` the error bound the other expansion carries.
    """

    Q: Any  # an array, or a LazyBlock (a tall compressor's left vectors, read by row chunks)
    Z: np.ndarray | None
    R: np.ndarray
    Y: np.ndarray | None
    m: int
    bound: Bound

    def coordinates(self) -> np.ndarray:
        """Return ``Z`` (the identity when ``Q`` holds the left vectors)."""
        return np.eye(self.Q.shape[1]) if self.Z is None else self.Z

    def left_vectors(self, load: Any = None) -> np.ndarray:
        """Return ``U_o = Q Z`` (column-major when formed here).

        ``load`` reads a :class:`~streamsvd.algebra.panels.lazy.LazyBlock` ``Q`` into
        memory (the receiving backend's ``in_memory``).
        """
        if isinstance(self.Q, LazyBlock):
            return cast(np.ndarray, load(self.Q))
        if self.Z is None:
            return self.Q
        if self.Q.shape[1] == 0 or self.Z.shape[1] == 0:
            return np.zeros((self.Q.shape[0], self.Z.shape[1]), order="F")
        return blas.dgemm(1.0, self.Q, self.Z)


def _merge_operand(other: Any, *, n: int, inner: InnerProduct, keep_rows: bool,
                   by_rows: bool = False) -> _MergeOperand:
    """Return what :meth:`StreamCompressor.merge` absorbs of ``other``.

    ``other`` is checked first: a compressor (whose parts hold a
    :class:`~streamsvd.stream.lifecycle.Lifecycle`) or an expansion of snapshots of size
    ``n`` in the inner product ``inner``. A compressor's basis in memory is used as it is;
    a basis elsewhere (panels) gives its left vectors: with ``by_rows`` (the receiving
    basis is in panels too) as a :class:`~streamsvd.algebra.panels.lazy.LazyBlock` that
    the merge reads by row chunks (never ``n x p`` in memory), else in memory.
    """
    life = getattr(other, "_life", None)
    if not isinstance(life, Lifecycle) and not isinstance(other, Expansion):
        raise InputError(
            f"`other` must be a StreamCompressor or an Expansion; got {type(other).__name__}."
        )
    if other.n != n:
        raise InputError(f"`other` must have snapshots of size {n}; got {other.n}.")
    check_same_inner(inner, other.inner, "other")
    if isinstance(life, Lifecycle):
        o = life.state
        if keep_rows and o.rows is None:
            raise InputError(
                "`other` keeps no right vectors (`right_vectors=False`) but this "
                "compressor does; merge compressors created alike."
            )
        Y_o = o.rows.value() if keep_rows and o.rows is not None else None
        coords, _, R = o.settled()
        if isinstance(o.basis, MemoryBasis):
            return _MergeOperand(o.basis.Q, coords, R, Y_o, o.m, o.bound)
        if by_rows and isinstance(o.basis, PanelBasis):
            left = LazyBlock(o.basis.lazy(coords), 0, "the left vectors of `other`")
            return _MergeOperand(left, None, R, Y_o, o.m, o.bound)
        return _MergeOperand(o.basis.lincomb(coords), None, R, Y_o, o.m, o.bound)
    expansion = cast(Expansion, other)  # what is not a compressor
    U_o, V_o = np.array(expansion.U, order="F"), np.array(expansion.V)
    if not keep_rows:
        return _MergeOperand(U_o, None, r_factor(V_o), None, V_o.shape[0], Bound())
    Y_o, R_o = np.linalg.qr(V_o)
    return _MergeOperand(U_o, None, R_o, Y_o, V_o.shape[0], Bound())


def _increment(s: State, U_k: Any, V_k: Any, coefficients: Any, *, n: int
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Check the arguments of :meth:`StreamCompressor.add` on the state ``s``; return arrays."""
    if s.rows is None:
        raise InputError(
            "`add` needs the right vectors, and this StreamCompressor keeps none "
            "(`right_vectors=False`); create it with `right_vectors=True`."
        )
    Uk = as_float_array(U_k, "U_k", ndim=2, rows=n)
    m = s.m if (s.m or s.rank) else None
    Vk = as_float_array(V_k, "V_k", ndim=2, rows=m, cols=Uk.shape[1])
    if coefficients is not None:
        return Uk, Vk, as_float_array(coefficients, "coefficients", ndim=2, rows=s.m,
                                      cols=s.rank)
    if Uk.shape[1] == 0:
        raise InputError(
            f"`U_k` must have at least one column (or pass `coefficients`); got shape "
            f"{Uk.shape}."
        )
    return Uk, Vk, None


def _merge_options(opts: StepOptions, *, spend_target: bool) -> StepOptions:
    """Return the step options of a merge: ``opts``, without the target unless it is spent."""
    if spend_target:
        return opts
    return dataclasses.replace(
        opts, truncation=dataclasses.replace(opts.truncation, target=None)
    )


def _final_options(opts: StepOptions, options: CompressorOptions, *, rule: str,
                   max_rank: int | None) -> StepOptions:
    """Return the step options of :meth:`StreamCompressor.finalize` (checking its arguments).

    ``opts`` are the compressor's step options, ``options`` its options.
    """
    cap = check_positive_int(max_rank, "max_rank", allow_none=True)
    return dataclasses.replace(
        opts, rule=check_choice(rule, "rule", RULES), sweeps=None,
        truncation=options.truncation(
            max_rank=options.max_rank if cap is None else cap, share=1.0),
    )
