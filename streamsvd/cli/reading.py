"""The commands that read STORE: ``streamsvd info | export | plot | check``.

Each opens STORE read-only (:func:`open_readonly`, whichever mode wrote it), so they run
while ``streamsvd ingest`` writes it. What they print is :mod:`streamsvd.cli.printing`'s;
the figure of ``plot`` is drawn by :mod:`streamsvd.plotting`.

Only the standard library is imported at module level (see :mod:`streamsvd.cli`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from streamsvd.cli.parsing import diagonal_as_weights, load_inner
from streamsvd.cli.printing import print_check, print_info, print_json
from streamsvd.errors import InputError, StoreError, StoreMismatchError

__all__ = ["check", "export", "info", "open_readonly", "plot"]


def open_readonly(path: Any, *, inner: Any = None) -> Any:
    """Open the compressor of a store read-only, whichever kind wrote it.

    ``inner``: the inner product, needed only for a store that does not keep its own.
    """
    from streamsvd.storage import open_storage

    if open_storage(path).is_file():
        raise StoreError(
            f"STORE {path} is a file; a basis store is a directory written by "
            "`streamsvd ingest`."
        )
    from streamsvd.stream.compressor import StreamCompressor

    try:
        return StreamCompressor.open(path, mode="r", inner=inner)
    except StoreMismatchError:
        from streamsvd.parallel.cluster import (
            open_compressor,  # a tall store: dask is needed to read it
        )

        # a tall store keeps weights: a matrix with only a diagonal is read as such
        return open_compressor(path, mode="r", inner=diagonal_as_weights(inner))


def info(args: Any) -> int:
    """Run ``streamsvd info``: the store's summary, as text or ``--json``."""
    from streamsvd.stream.summary import summary_of

    with open_readonly(args.store, inner=load_inner(args)) as sc:
        summary = summary_of(sc)
    if args.json:
        print_json(summary)
    else:
        print_info(summary)
    return 0


def export(args: Any) -> int:
    """Run ``streamsvd export``: write U, V, the amplitudes and the bound to OUT."""
    out = Path(args.out)
    if out.suffix not in (".npz", ".h5", ".hdf5"):
        raise InputError(f"OUT must end with .npz, .h5 or .hdf5; got {out.name!r}.")
    import numpy as np

    with open_readonly(args.store, inner=load_inner(args)) as sc:
        e = sc.expansion
        bound = sc.error_bound
    data = {"U": e.U, "V": e.V, "amplitudes": e.amplitudes, "error_bound": np.array(bound)}
    if out.suffix == ".npz":
        np.savez(out, **data)
    else:
        import h5py

        with h5py.File(out, "w") as h5:
            for k, v in data.items():
                h5.create_dataset(k, data=v)
    print(f"wrote {out} (U {e.U.shape}, V {e.V.shape})")
    return 0


def plot(args: Any) -> int:
    """Run ``streamsvd plot``: draw the store's figure to OUT."""
    from streamsvd.plotting import compressor_figure

    out = Path(args.out)
    with open_readonly(args.store, inner=load_inner(args)) as sc:
        fig = compressor_figure(sc, name=Path(str(args.store).rstrip("/")).name)
    fig.savefig(out, dpi=120)
    print(f"wrote {out}")
    return 0


def check(args: Any) -> int:
    """Verify every checksum of STORE: one line per problem (exit 2), or what verified (0)."""
    from streamsvd.parallel.cluster import check_store
    from streamsvd.storage import open_storage

    report = check_store(open_storage(args.store))
    print_check(report)
    return 2 if report.problems else 0
