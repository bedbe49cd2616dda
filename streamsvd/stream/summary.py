"""What ``streamsvd info --json`` prints of a compressor, and the final sweeps' progress bar."""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from streamsvd.stream.compressor import StreamCompressor

__all__ = ["summary_of"]


def summary_of(sc: StreamCompressor) -> dict[str, Any]:
    """Return what ``streamsvd info --json`` prints of a compressor (JSON-able)."""
    return {
        "store": sc.store_path, "n": sc.n, "n_seen": sc.n_seen, "rank": sc.rank,
        "source_offset": sc.source_offset, "updates": len(sc.history),
        "finalized": sc.finalized, "error_bound": sc.error_bound,
        "discarded_norm": sc.discarded_norm, "orthogonality": sc.orthogonality_error(),
        "error_in_measure": sc.error_in_measure, "target_met": sc.target_met,
        "target_missed_by": sc.target_missed_by,
        "n_absorbed": sc.n_absorbed, "removed": sc.removed.tolist(),
        "options": sc.options.as_dict(), "inner": repr(sc.inner),
        "source": None if sc.source_record is None else sc.source_record.to_attrs(),
        "amplitudes_head": sc.amplitudes[:10].tolist(),
        "dynamics": {"recorded": sc.options.dynamics, "trajectory_starts":
                     sc.trajectory_starts.tolist()},
    }


@contextlib.contextmanager
def _sweep_bar(rank: int, show: bool) -> Iterator[Callable[[int, float], None] | None]:
    """Yield the ``on_sweep`` callback of a progress bar of the final sweeps (or None)."""
    if not show:
        yield None
        return
    from tqdm import tqdm

    with tqdm(desc=f"final sweeps ({rank} terms)", unit="sweep", file=sys.stderr,
              dynamic_ncols=True) as bar:
        def on_sweep(done: int, max_cosine: float) -> None:
            bar.set_postfix(max_cosine=f"{max_cosine:.1e}", refresh=False)
            bar.update(done - bar.n)

        yield on_sweep
