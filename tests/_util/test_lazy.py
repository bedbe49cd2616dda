"""Modules named at a module's top and imported by the first call that uses them."""

import subprocess
import sys

import numpy as np
import scipy.sparse as sp

from streamsvd._util.lazy import lazy_module


def test_the_inner_products_import_scipy_sparse_only_for_a_sparse_matrix():
    code = ("import sys; import streamsvd.algebra.inner as inner, streamsvd.algebra.spd; "
            "import numpy as np; inner.as_inner(None); inner.as_inner(np.ones(3)); "
            "print('scipy.sparse' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)
    assert out.stdout.strip() == "False"


def test_a_lazy_module_is_the_module_once_imported():
    lazy = lazy_module("scipy.sparse", absent={"issparse": lambda x: False})
    M = sp.eye(3, format="csr")
    assert lazy.issparse(M) and not lazy.issparse(np.eye(3))
    assert lazy.csr_array is sp.csr_array
    assert "scipy.sparse" in repr(lazy)
