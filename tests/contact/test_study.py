"""The billet study's module (contact.study): its lazy export and its summary's JSON.

The study itself (every solver, Figs. 5-9) runs in the slow tier
(tests/slow/examples/test_contact_examples.py).
"""

import json

import numpy as np
import pytest

import contact
from contact import study


def test_the_study_is_exported_lazily_by_the_package():
    assert contact.billet_study is study.billet_study


def test_the_summary_writes_numpy_numbers_as_json_and_refuses_other_objects():
    doc = {"k": np.int64(3), "x": np.float32(0.5), "v": np.arange(3.0)}
    assert json.loads(json.dumps(doc, default=study._json_default)) == {
        "k": 3, "x": 0.5, "v": [0.0, 1.0, 2.0],
    }
    assert study._finite(np.inf) is None and study._finite(np.float64(2.0)) == 2.0
    with pytest.raises(TypeError, match="cannot serialise object"):
        study._json_default(object())
