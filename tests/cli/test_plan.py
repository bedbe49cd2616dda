"""The plan of ``streamsvd ingest``: decided once, SOURCE opened once, nothing read twice."""

import dataclasses

import numpy as np
import pytest

import streamsvd.io.open
from streamsvd.cli import main
from streamsvd.cli.parsing import DEFAULT_BLOCK, build_parser, locate
from streamsvd.cli.plan import IngestPlan, plan_ingest
from streamsvd.errors import InputError


def parsed(*argv):
    args = build_parser().parse_args(["ingest", *map(str, argv)])
    locate(args)
    return args


@pytest.fixture
def source(tmp_path, rng):
    path = tmp_path / "a.npy"
    np.save(path, rng.standard_normal((40, 12)))
    return path


def test_a_new_store_gets_the_command_defaults_and_the_source_record(tmp_path, source):
    args = parsed(source, tmp_path / "s.zarr", "--max-rank", "5", "--quiet")
    with streamsvd.io.open.open_source(str(source)) as src:
        plan = plan_ingest(args, src)
    assert isinstance(plan, IngestPlan)
    assert (plan.mode, plan.resume, plan.block, plan.progress) == ("memory", False,
                                                                   DEFAULT_BLOCK, False)
    assert plan.options["max_rank"] == 5 and plan.options["inner"] is None
    assert plan.record.shape == (40, 12)
    with pytest.raises(dataclasses.FrozenInstanceError):
        plan.block = 3  # type: ignore[misc]


@pytest.mark.parametrize(("extra", "mode"), [(["--scheduler", "threads"], "tree"),
                                             (["--tall"], "tall")])
def test_the_dask_options_travel_in_the_plan(tmp_path, source, extra, mode):
    args = parsed(source, tmp_path / "s.zarr", *extra)
    with streamsvd.io.open.open_source(str(source)) as src:
        plan = plan_ingest(args, src)
    assert plan.mode == mode
    assert set(plan.dask) == {"scheduler", "workers", "leaf_columns", "chunk_rows"}


def test_an_option_of_another_mode_is_refused_before_the_store_is_touched(tmp_path, source):
    store = tmp_path / "s.zarr"
    args = parsed(source, store, "--chunk-rows", "10")
    with streamsvd.io.open.open_source(str(source)) as src, \
            pytest.raises(InputError, match="--chunk-rows"):
        plan_ingest(args, src)
    assert not store.exists()


def test_ingest_opens_source_once(tmp_path, source, monkeypatch, capsys):
    opened = []
    real = streamsvd.io.open.open_source

    def counting(*args, **kwargs):
        opened.append(args)
        return real(*args, **kwargs)

    monkeypatch.setattr(streamsvd.io.open, "open_source", counting)
    assert main(["ingest", str(source), str(tmp_path / "s.zarr"), "--quiet"]) == 0
    assert len(opened) == 1
    assert main(["ingest", str(source), str(tmp_path / "s.zarr"), "--resume", "--quiet"]) == 0
    assert len(opened) == 2
