"""The package's layers: faces that re-export, the public API, the old module paths."""

import importlib
import pkgutil
import subprocess
import sys

import pytest

import streamsvd

LAYERS = ["algebra", "algebra.panels", "engine", "io", "linalg", "parallel", "sklearn",
          "stream"]
OLD_PATHS = {"basis": "algebra.memory", "bound": "engine.bound",
             "estimator": "sklearn.estimator", "sources": "io.sources",
             "parallel_tree": "parallel.tree", "gram_schmidt": "linalg.gram_schmidt"}


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
    home = importlib.import_module(f"streamsvd.{OLD_PATHS[old]}")
    assert module.__all__ == list(home.__all__)
    for name in home.__all__:
        assert getattr(module, name) is getattr(home, name)
    assert home.__name__ == f"streamsvd.{OLD_PATHS[old]}"  # the home is left as it is


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
