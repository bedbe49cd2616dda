"""The package's layers: faces that re-export, the public API, the old module paths."""

import importlib
import pkgutil
import subprocess
import sys

import pytest

import streamsvd

LAYERS = ["algebra", "algebra.panels", "engine", "io", "linalg", "parallel", "sklearn",
          "stream"]
OLD_PATHS = {"basis": ("algebra.memory", "algebra.interface", "algebra.buffer"),
             "bound": "engine.bound",
             "estimator": "sklearn.estimator",
             "sources": ("io.sources", "io.open", "algebra.panels.lazy", "io.formats"),
             "parallel_tree": ("parallel.tree", "parallel.spec"),
             "parallel_tall": ("parallel.tall", "algebra.panels.backend"),
             "gram_schmidt": ("linalg.gram_schmidt", "linalg.extend", "linalg.rejection"),
             "inner": ("algebra.inner", "io.inner_file", "algebra.spd"),
             "locks": ("storage.lockfile", "storage.lease")}
# the public names of the flat modules split in the move: their aliases still read them
OLD_NAMES = {"basis": ["Backend", "BasisBackend", "DeferredGram", "MEMORY_KIND", "MemoryBackend",
                       "MemoryBasis"],
             "sources": ["LazyBlock", "Source", "open_source", "open_zarr_url"],
             "parallel_tree": ["COMPRESSOR_OPTIONS", "SourceSpec", "tree_compress"],
             "parallel_tall": ["DEFAULT_CHUNK_ROWS", "KIND", "PanelBackend", "TallCompressor"],
             "locks": ["LEASE_SECONDS", "FileLock", "Lease"],
             "inner": ["InnerProduct", "MatrixInner", "as_inner", "inner_arrays", "load_inner"]}


def test_every_public_name_of_the_package_resolves():
    for name in streamsvd.__all__:
        assert getattr(streamsvd, name) is not None, name
    assert streamsvd.compress.__module__ == "streamsvd.linalg.compress"
    assert streamsvd.StreamCompressor.__module__ == "streamsvd.stream.compressor"


@pytest.mark.parametrize("layer", LAYERS)
def test_each_layer_re_exports_the_names_of_its_modules(layer):
    face = importlib.import_module(f"streamsvd.{layer}")
    assert face.__all__ and set(face.__all__) <= set(dir(face))
    for name in face.__all__:
        value = getattr(face, name)
        home = importlib.import_module(f"streamsvd.{layer}.{face._EXPORTS[name]}")
        assert value is getattr(home, name), name
    with pytest.raises(AttributeError, match="has no attribute 'nothing'"):
        face.nothing  # noqa: B018


@pytest.mark.parametrize("old", sorted(OLD_PATHS))
def test_an_old_module_path_reads_its_new_home(old):
    module = importlib.import_module(f"streamsvd.{old}")
    paths = OLD_PATHS[old] if isinstance(OLD_PATHS[old], tuple) else (OLD_PATHS[old],)
    homes = [importlib.import_module(f"streamsvd.{path}") for path in paths]
    names = [name for home in homes for name in home.__all__]
    assert module.__all__ == list(dict.fromkeys(names))
    assert set(OLD_NAMES.get(old, ())) <= set(module.__all__)
    for name in names:  # a name is read from the first home that has it
        first = next(home for home in homes if hasattr(home, name))
        assert getattr(module, name) is getattr(first, name)
    for home, path in zip(homes, paths, strict=True):
        assert home.__name__ == f"streamsvd.{path}"  # the home is left as it is
    assert getattr(streamsvd, old).__all__ == module.__all__  # the attribute reads them too


@pytest.mark.slow
def test_every_module_imports_on_its_own():
    """Each module imports first in a fresh interpreter: no circle through a face."""
    names = [m.name for m in pkgutil.walk_packages(streamsvd.__path__, "streamsvd.")
             if not m.name.endswith("__main__")]
    script = ("import importlib, sys\n"
              "for name in sys.argv[1:]:\n"
              "    importlib.import_module(name)\n")
    for name in names:
        proc = subprocess.run([sys.executable, "-c", script, name], capture_output=True,
                              text=True)
        assert proc.returncode == 0, (name, proc.stderr[-2000:])
