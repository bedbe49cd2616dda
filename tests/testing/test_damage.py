"""The damage kit of the fault tests (streamsvd.testing.damage): every kind is caught by check."""

import numpy as np
import pytest

from streamsvd.storage import open_storage
from streamsvd.store import GENERATIONS, BasisStore, check_store
from streamsvd.testing.damage import GENERATION_DAMAGE, damage_generation


@pytest.mark.parametrize("kind", GENERATION_DAMAGE)
def test_each_kind_of_damage_is_reported_by_check(tmp_path, kind):
    path = tmp_path / "s.zarr"
    with BasisStore.create(path, n=50, inner_fingerprint="f" * 64) as store:
        store.commit({"U": np.ones((50, 3))}, {"n_seen": 3})
    assert check_store(open_storage(path)).healthy
    damage_generation(path / GENERATIONS / "g00000001", kind)
    assert not check_store(open_storage(path)).healthy


def test_an_unknown_kind_is_refused(tmp_path):
    with pytest.raises(ValueError, match="`kind` must be one of"):
        damage_generation(tmp_path, "burn")
