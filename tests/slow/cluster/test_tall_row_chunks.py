"""The tall modes on isolated workers read and write by row chunks, and only there.

Every read of the source's columns (:class:`streamsvd.io.sources._ChunkReader`) and
every read and write of a panel on the object store (:mod:`streamsvd.algebra.panels.zarr_io`)
is recorded, in each worker process and in the client, with the number of rows it
touched: no access spans more than ``chunk_rows`` rows, every block is read whole by the
workers, and the client reads no row of the source or of a panel (for the tall tree:
neither the leaves nor the copy of the root into the store nor its finalisation).
"""

import sys

import numpy as np
import pytest

from streamsvd.testing import with_spectrum

pytest.importorskip("distributed")
pytest.importorskip("moto.server")
pytest.importorskip("s3fs")

import cloudpickle  # noqa: E402  (distributed's)

# the workers run in directories of their own, where this module cannot be imported:
# its functions (_instrument, _touched) travel by value
cloudpickle.register_pickle_by_value(sys.modules[__name__])

BUCKET = "row-chunk-tests"
ROWS = 64  # chunk_rows of the runs; n = 400 is not a multiple of it


def _instrument() -> None:
    """Record the rows of every source read and panel access of this process (idempotent)."""
    from streamsvd.algebra.panels import zarr_io
    from streamsvd.io import sources

    if hasattr(sources, "_rows_touched"):
        sources._rows_touched.clear()
        return
    touched: list[tuple[str, int]] = []
    sources._rows_touched = touched

    def rows(key, n):
        first = key[0] if isinstance(key, tuple) else key
        a, b, _ = first.indices(n)
        return b - a

    get = sources._ChunkReader.__getitem__

    def source_get(self, key):
        touched.append(("source", rows(key, self.shape[0])))
        return get(self, key)

    read, write = zarr_io.read, zarr_io.write

    def panel_read(array, key):
        touched.append(("panel read", rows(key, array.shape[0])))
        return read(array, key)

    def panel_write(array, key, value):
        touched.append(("panel write", rows(key, array.shape[0])))
        return write(array, key, value)

    sources._ChunkReader.__getitem__ = source_get
    zarr_io.read, zarr_io.write = panel_read, panel_write


def _touched() -> list[tuple[str, int]]:
    from streamsvd.io import sources

    return list(getattr(sources, "_rows_touched", []))


@pytest.fixture(scope="module")
def setting(s3_environment, workers_environment):
    import s3fs
    import zarr
    from zarr.storage import FsspecStore

    from streamsvd.testing.cluster import start

    s3fs.S3FileSystem().mkdir(BUCKET)
    A = with_spectrum(np.logspace(0, -9, 30), 400, 60, np.random.default_rng(3))
    url = f"s3://{BUCKET}/a.zarr"
    arr = zarr.create_array(store=FsspecStore.from_url(url, read_only=False),
                            shape=A.shape, dtype=A.dtype, chunks=(100, 10))
    arr[...] = A
    running = start(workers=2, env=workers_environment(**s3_environment))
    yield A, url, running
    running.stop()


@pytest.mark.parametrize("mode", ["tall", "tall_tree"])
def test_tall_modes_touch_one_row_chunk_per_access_on_the_workers(setting, mode):
    from distributed import Client

    from streamsvd.parallel import tall_compress, tall_tree_compress, tree_compress

    A, url, cluster = setting
    with Client(cluster.address, timeout="30s") as client:
        client.run(_instrument)
        _instrument()
        opts = {"block": 10, "chunk_rows": ROWS, "max_rank": 6, "finalize": True,
                "client": client, "store": f"s3://{BUCKET}/{mode}"}
        if mode == "tall":
            sc = tall_compress(url, **opts)
        else:
            sc = tall_tree_compress(url, workdir=f"s3://{BUCKET}/{mode}-work",
                                    leaf_columns=30, **opts)
        on_workers = client.run(_touched)
        here = _touched()
        s = np.array(sc.amplitudes)
        sc.close()
    assert here == []  # the client read no row of the source or of a panel
    seen = [t for ts in on_workers.values() for t in ts]
    assert max(r for _, r in seen) <= ROWS
    assert sum(r for kind, r in seen if kind == "source") >= A.size // 10  # n rows a block
    assert {kind for kind, _ in seen} == {"source", "panel read", "panel write"}
    assert all(ts for ts in on_workers.values())  # both workers took part
    ref = tree_compress(A, block=10, leaf_columns=30, max_rank=6, finalize=True)
    tol = 50 * max(A.shape) * np.finfo(float).eps
    assert s.size == 6
    assert np.abs(s - ref.amplitudes).max() <= tol * ref.amplitudes[0]
