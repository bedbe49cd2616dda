"""The benchmark suite: its studies, and the results files they write.

A *study* is one page of the benchmark record: one or more scripts of ``bench/`` (each
with a ``main(argv)``), the prose in ``bench/studies/NAME.md`` (what it measures, the
commands, the recorded runs and their reading) and the files it wrote to
``bench/results/``. :data:`STUDIES` lists them in the order of the pages;
``python -m bench`` runs their scripts and ``python -m bench pages`` renders their pages.

Every run writes its numbers as JSON in one envelope (``_common.Run``)::

    {"format": "streamsvd-bench/1", "study": ..., "argv": [...], "date": ...,
     "seconds": ..., "machine": {..., "load_before": [...], "load_after": [...]},
     "versions": {...}, "git": {"commit": ..., "dirty": ...}, "results": PAYLOAD}

Files written before the envelope hold the payload alone; :func:`read_run` reads both.
This module uses the standard library only, so that the docs build can import it.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

BENCH_DIR = Path(__file__).resolve().parent
RESULTS_DIR = BENCH_DIR / "results"
STUDIES_DIR = BENCH_DIR / "studies"
FORMAT = "streamsvd-bench/1"


@dataclass(frozen=True)
class Column:
    """One column of a results table: a header and where its value sits in a row.

    ``key`` is a ``/``-separated path into the row (``commit_seconds/median``); ``fmt`` a
    format spec for numbers (``.3g``); ``scale`` multiplies a number before formatting.
    """

    header: str
    key: str
    fmt: str = ""
    scale: float = 1.0


@dataclass(frozen=True)
class Table:
    """The headline numbers of one results file, as a table.

    ``rows`` is a ``/``-separated path from the payload to the rows: a name descends into
    a mapping (over every item of a list met on the way, whose plain fields each row
    keeps); ``*label`` runs over the items of a mapping or list and records the key or
    index under ``label``. The value reached is one row (a mapping) or a list of rows.
    """

    source: str
    rows: str
    columns: tuple[Column, ...]
    title: str = ""


def table(source: str, rows: str, columns: list[tuple[Any, ...]], title: str = "") -> Table:
    """Build a :class:`Table` from ``(header, key[, fmt[, scale]])`` tuples."""
    return Table(source, rows, tuple(Column(*c) for c in columns), title)


@dataclass(frozen=True)
class Study:
    """One page of the record: its scripts, prose, figures, result files and tables.

    ``shown`` are figures drawn on the page; ``files`` glob patterns (relative to
    ``bench/results``, without the suffix) of every figure and JSON of its runs; the
    figures among them that are not shown are listed as links.
    """

    name: str
    title: str
    scripts: tuple[str, ...]
    shown: tuple[str, ...] = ()
    files: tuple[str, ...] = ()
    tables: tuple[Table, ...] = field(default_factory=tuple)

    @property
    def prose(self) -> Path:
        """The Markdown source of the page's text: ``bench/studies/NAME.md``."""
        return STUDIES_DIR / f"{self.name}.md"

    def result_files(self, suffix: str, results: Path = RESULTS_DIR) -> list[Path]:
        """The files of ``results`` with this suffix that one of :attr:`files` matches."""
        found = {p for pattern in self.files for p in results.glob(pattern + suffix)}
        return sorted(found, key=lambda p: p.relative_to(results).as_posix())


STUDIES: tuple[Study, ...] = (
    Study("fig1-pair-dynamics", "Fig. 1: pair dynamics", ("fig1_pair_dynamics",),
          shown=("fig1_pair_dynamics.png",), files=("fig1_pair_dynamics*",),
          tables=(table("fig1_pair_dynamics.json", "trajectories", [
              ("eta_0", "eta0", "g"), ("alpha_0", "alpha0", "g"), ("delta", "delta", ".4g"),
              ("eta limit", "eta_limit", ".4g"), ("observed rate", "observed_rate", ".4g"),
              ("max dev. eta", "max_dev_eta", ".1e"), ("max dev. alpha", "max_dev_alpha", ".1e"),
          ]),)),
    Study("fig3-rbs480a", "Figs 2-3: rbs480a", ("fig3_rbs480a",),
          shown=("fig3_rbs480a.png", "fig2_rbs480a_spectra.png"),
          files=("fig3_rbs480a*", "fig2_rbs480a*")),
    Study("speed-vs-error", "Speed against error", ("speed_vs_error",),
          shown=("speed_vs_error_generated.png", "speed_vs_error_generated_blas1.png"),
          files=("speed_vs_error*",)),
    Study("engine-benchmark", "One update (engine)", ("engine_benchmark",),
          shown=("engine_benchmark.png",), files=("engine_benchmark*",),
          tables=(table("engine_benchmark.json", "block", [
              ("n", "n"), ("threads", "threads"), ("method", "method"),
              ("ms / update", "median_update_s", ".1f", 1e3),
              ("GFLOP/s (floor)", "gflops_floor", ".1f"), ("sv error", "sv_rel_error", ".1e"),
              ("‖UᵀU − I‖", "orthogonality", ".1e"), ("peak / data", "peak_over_data", ".2f"),
          ], "block updates"), table("engine_benchmark.json", "long/*stream", [
              ("stream", "stream"), ("first 1000 (µs)", "first_1000_mean_s", ".1f", 1e6),
              ("last 1000 (µs)", "last_1000_mean_s", ".1f", 1e6), ("last / first", "ratio", ".2f"),
              ("CPU last / first", "cpu_ratio", ".2f"),
              ("max ‖UᵀU − I‖", "max_orthogonality", ".1e"),
          ], "long stream"))),
    Study("estimator-benchmark", "Estimator", ("estimator_benchmark",),
          shown=("estimator_benchmark.png",), files=("estimator_benchmark*",),
          tables=(table("estimator_benchmark.json", "results/*estimator/*samples", [
              ("estimator", "estimator"), ("samples seen", "samples"),
              ("CPU ms / call", "cpu_s", ".3f", 1e3), ("wall ms / call", "wall_s", ".3f", 1e3),
          ]),)),
    Study("stream-benchmark", "Streaming against IncrementalPCA", ("stream_benchmark",),
          shown=("stream_benchmark.png", "stream_benchmark_xeon_kept.png"),
          files=("stream_benchmark*",),
          tables=(table("stream_benchmark.json", "configurations/*configuration/methods/*m", [
              ("configuration", "configuration"), ("method", "label"),
              ("ms / update", "median_update_s", ".3g", 1e3),
              ("recon / opt", "recon_over_opt", ".4f"),
              ("sv error", "sv_rel_err", ".1e"), ("‖UᵀU − I‖", "orthogonality", ".1e"),
          ]),)),
    Study("store-benchmark", "Store commits", ("store_benchmark",),
          shown=("store_benchmark.png", "store_benchmark_mass.png"),
          files=("store_benchmark*",),
          tables=(table("store_benchmark.json", "results", [
              ("m", "m"), ("V0 MB", "V0_bytes", ".2f", 1e-6),
              ("commit ms (median)", "commit_seconds/median", ".1f", 1e3),
              ("commit ms (p90)", "commit_seconds/p90", ".1f", 1e3),
              ("update in memory ms", "update_in_memory_seconds/median", ".2f", 1e3),
              ("written B (median)", "written_bytes/median", ".0f"),
          ]),)),
    Study("final-benchmark", "The SVD by default", ("final_benchmark",),
          shown=("final_benchmark.png",), files=("final_benchmark*",)),
    Study("object-store-benchmark", "Object store", ("object_store_benchmark",),
          shown=("object_store_benchmark.png",), files=("object_store_benchmark*",),
          tables=(table("object_store_benchmark.json", "results", [
              ("store", "store"), ("create s", "create_seconds", ".3f"),
              ("commit ms (median)", "commit_seconds/median", ".1f", 1e3),
              ("commit ms (max)", "commit_seconds/max", ".1f", 1e3),
              ("reopen ms", "reopen_seconds", ".1f", 1e3), ("read ms", "read_seconds", ".1f", 1e3),
              ("source read s", "source_read/wall", ".2f"),
              ("source read CPU s", "source_read/cpu", ".2f"),
              ("tall stream s", "tall_stream/wall", ".2f"),
              ("tall stream CPU s", "tall_stream/cpu", ".2f"),
          ]),)),
    Study("tall-tree-checkpoints", "Tall-tree checkpoints",
          ("tall_tree_checkpoints_benchmark",),
          shown=("tall_tree_checkpoints_benchmark.png",),
          files=("tall_tree_checkpoints_benchmark*",),
          tables=(table("tall_tree_checkpoints_benchmark.json", "results", [
              ("contender", "contender"), ("n", "n"), ("m", "m"),
              ("wall s (median)", "wall_seconds", ".2f"),
              ("CPU s (median)", "cpu_seconds", ".2f"), ("repeats", "repeats"),
          ]),)),
    Study("fault-campaign", "Fault campaign", ("fault_campaign",), files=("fault_campaign*",),
          tables=(table("fault_campaign.json", "counts", [
              ("kind", "kind"), ("where", "where"), ("scenarios", "count"),
              ("failed", "failed"),
          ]),)),
    Study("contact", "contact solvers",
          ("bench_contact_scale", "bench_contact_pgd", "bench_contact_subspace"),
          shown=("contact/scale.png", "contact/pgd_choices.png"),
          files=("contact/*", "contact/large_trunc_*/*"),
          tables=(table("contact/pgd_choices.json", "rows", [
              ("variant", "variant"), ("CPU ms", "cpu_s", ".1f", 1e3),
              ("iterations", "iterations"), ("converged", "converged"),
              ("error u", "error_u", ".1e"), ("error forces", "error_forces", ".1e"),
          ], "LATIN-PGD's choices"),)),
    Study("guarantee-cost", "What the guarantees cost", ("guarantee_cost",),
          shown=("guarantee_cost.png",), files=("guarantee_cost*",),
          tables=(table("guarantee_cost.json", "rows", [
              ("case", "case"), ("kind", "kind"), ("measure", "measure"),
              ("target", "target", "g"), ("optimum", "optimal"), ("modes", "modes"),
              ("certified / target", "certified_over_target", ".3f"),
              ("true / target", "true_over_target", ".3f"), ("CPU s", "seconds", ".2f"),
          ]),)),
    Study("tight-targets", "Tight targets, a rank cap and a full SVD", ("tight_targets",),
          shown=("tight_targets.png", "tight_targets_ingest.png"), files=("tight_targets*",),
          tables=(table("tight_targets.json", "targets", [
              ("case", "case"), ("measure", "measure"), ("target", "target", "g"),
              ("streamsvd CPU s", "streamsvd_cpu", ".3f"), ("HAPOD CPU s", "hapod_cpu", ".3f"),
              ("ratio", "ratio", ".2f"), ("modes", "streamsvd_modes"),
              ("HAPOD modes", "hapod_modes"), ("true / target", "streamsvd_error", ".3f"),
              ("bound / target", "bound", ".3f"), ("load", "load", ".1f"),
          ], "targets against inc_vectorarray_hapod"), table("tight_targets.json", "cap", [
              ("contender", "contender"), ("CPU s", "cpu", ".2f"), ("sv error", "sv_err", ".1e"),
              ("err / opt", "err_opt", ".7f"), ("load", "load", ".1f"),
          ], "rank cap 60"), table("tight_targets.json", "rbs480a", [
              ("method", "method"), ("CPU s", "cpu", ".3f"), ("x gesdd", "over_gesdd", ".2f"),
              ("sweeps", "sweeps"), ("residual", "residual", ".2f"),
              ("orth. V", "orthogonality_v", ".2f"), ("sv", "singular_values", ".2f"),
          ], "rbs480a"), table("tight_targets_ingest.json", "ingest", [
              ("store", "store"), ("contender", "contender"), ("wall s", "wall", ".2f"),
              ("CPU s", "cpu", ".2f"),
              ("wall / memory", "wall_over_memory", ".2f"),
              ("CPU / memory", "cpu_over_memory", ".2f"), ("load", "load", ".1f"),
          ], "ingest 200000 x 500"))),
    Study("target-benchmark", "A relative target error", ("target_benchmark",),
          shown=("target_benchmark.png",), files=("target_benchmark*",),
          tables=(table("target_benchmark.json", "results", [
              ("target", "target", "g"), ("mode", "mode"), ("modes", "modes"),
              ("optimum", "optimum"), ("true rel. error", "true_error", ".3e"),
              ("bound / true", "bound_over_true", ".3f"), ("time s", "seconds", ".2f"),
              ("load", "load", ".1f"),
          ]),)),
    Study("window-benchmark", "Windows and forgetting", ("window_benchmark",),
          shown=("window_benchmark.png",), files=("window_benchmark*",),
          tables=(table("window_benchmark.json", "runs", [
              ("window W", "W"), ("block b", "b"), ("n", "n"), ("m", "m"),
              ("ms / update", "seconds_per_update", ".1f", 1e3),
              ("first tenth ms", "first_tenth", ".1f", 1e3),
              ("last tenth ms", "last_tenth", ".1f", 1e3),
          ]),)),
    Study("merge-benchmark", "Merges", ("merge_benchmark",),
          shown=("merge_benchmark.png",), files=("merge_benchmark*",),
          tables=(table("merge_benchmark.json", "rows", [
              ("path", "path"), ("seconds", "seconds", ".3f"), ("passes", "passes"),
              ("sweeps", "sweeps"), ("err / opt", "err_over_opt", ".7f"),
              ("sv error", "sv_error", ".1e"), ("‖UᵀU − I‖", "orthogonality", ".1e"),
              ("load", "load", ".1f"),
          ]),)),
    Study("commit-benchmark", "Committing a large basis", ("commit_benchmark",),
          shown=("commit_benchmark.png",), files=("commit_benchmark*",),
          tables=(table("commit_benchmark.json", "rows", [
              ("layout", "layout"), ("commit s", "commit_s", ".3f"),
              ("MB/s", "commit_mb_s", ".0f"), ("commit CPU s", "commit_cpu_s", ".3f"),
              ("read s", "read_s", ".3f"), ("read MB/s", "read_mb_s", ".0f"),
              ("bytes / data", "bytes_over_data", ".3f"), ("load", "load", ".1f"),
          ]),)),
    Study("hapod-benchmark", "Against pyMOR's HAPOD", ("hapod_benchmark",),
          shown=("hapod_benchmark.png", "hapod_benchmark_before.png"),
          files=("hapod_benchmark*",),
          tables=(table("hapod_benchmark.json", "cases/*case/results/*run", [
              ("case", "case"), ("method@target", "run"), ("seconds", "seconds", ".3f"),
              ("modes", "modes"), ("error", "error", ".3e"), ("load", "load", ".1f"),
          ]),)),
    Study("outofcore-benchmark", "Out of core",
          ("outofcore_benchmark", "zarr_io_benchmark", "tall_narrow_blocks"),
          shown=("outofcore_benchmark.png", "outofcore_benchmark_auto.png",
                 "tall_narrow_blocks.png"),
          files=("outofcore_benchmark*", "zarr_io_benchmark*", "tall_narrow_blocks*"),
          tables=(table("outofcore_benchmark.json", "cases/runs", [
              ("n", "n"), ("m", "m"), ("dtype", "dtype"), ("method", "method"),
              ("seconds", "seconds", ".1f"), ("x read", "vs_read", ".2f"),
              ("peak RSS MB", "peak_rss_mb", ".0f"), ("CPU s", "cpu_seconds", ".1f"),
              ("err / opt", "error_over_optimum", ".9f"), ("load", "load_before", ".1f"),
          ]),)),
    Study("dmd-benchmark", "Streaming DMD against PyDMD and odmd", ("dmd_benchmark",),
          shown=("dmd_benchmark.png",), files=("dmd_benchmark*",),
          tables=(
              table("dmd_benchmark.json", "accuracy", [
                  ("noise", "noise", ".0e"), ("delta", "delta", ".2e"),
                  ("stream error", "stream", ".2e"), ("stream max eta", "stream_max_eta", ".2e"),
                  ("certified", "stream_certified"), ("PyDMD error", "pydmd", ".2e"),
                  ("odmd POD error", "odmd_pod", ".2e"), ("odmd full error", "odmd_full", ".2e"),
              ], "largest eigenvalue error"),
              table("dmd_benchmark.json", "cost", [
                  ("n", "n"), ("m", "m"),
                  ("stream ms/snap", "stream_dynamics/cpu_per_snapshot", ".3f", 1e3),
                  ("stream MB", "stream_dynamics/peak_mb", ".1f"),
                  ("no dynamics ms/snap", "stream_plain/cpu_per_snapshot", ".3f", 1e3),
                  ("dyn / plain", "dynamics_over_plain", ".2f"),
                  ("query ms", "stream_query/cpu_per_snapshot", ".1f", 1e3),
                  ("PyDMD ms/snap", "pydmd/cpu_per_snapshot", ".3f", 1e3),
                  ("PyDMD MB", "pydmd/peak_mb", ".0f"),
                  ("odmd ms/snap", "odmd_full/cpu_per_snapshot", ".3f", 1e3),
                  ("odmd MB", "odmd_full/peak_mb", ".0f"),
              ], "cost (CPU; peak of the memory allocated)"),
          )),
    Study("dask", "On dask (out of core, cluster)", ("bench_dask",),
          shown=("bench_dask.png",), files=("bench_dask*",),
          tables=(table("bench_dask.json", "runs", [
              ("method", "method"), ("workers", "workers"), ("time s", "seconds", ".1f"),
              ("peak GB", "peak_rss", ".2f", 1e-9), ("x read", "throughput_vs_read", ".2f"),
              ("err / opt", "error_over_optimal", ".9f"), ("sv error", "sv_error", ".1e"),
              ("update s", "update_seconds", ".2f"),
          ]),)),
    Study("cluster-benchmark", "On a shared-nothing cluster",
          ("cluster_benchmark", "cluster_memory"),
          shown=("cluster_benchmark.png", "cluster_benchmark_n1e5.png", "cluster_memory.png"),
          files=("cluster_benchmark*", "cluster_memory*"),
          tables=(*(table(f"{name}.json", "summary/*contender", [
              ("contender", "contender"), ("time s", "seconds", ".1f"),
              ("client CPU s", "client_cpu", ".1f"), ("modes", "modes"),
              ("err / opt", "err_over_opt", ".6f"),
              ("client +MB", "client_growth_mb", ".0f"),
              ("worker MB", "worker_peak_mb", ".0f"), ("load", "load", ".1f"),
          ], title) for name, title in (
              ("cluster_benchmark", "20000 x 2000"), ("cluster_benchmark_n1e5", "100000 x 500"),
          )), table("cluster_memory.json", "summary", [
              ("contender", "contender"), ("n", "n"), ("time s", "seconds", ".1f"),
              ("worker CPU / wall", "parallelism", ".2f"),
              ("worker MB (each)", "worker_peaks"),
              ("scheduler MB", "scheduler_peak_mb", ".0f"),
              ("client MB", "client_peak_mb", ".0f"),
              ("client +MB", "client_growth_mb", ".0f"),
              ("modes", "modes"), ("s vs svd_compressed", "s_rel_diff", ".1e"),
              ("load", "load", ".1f"),
          ], "peak memory against n, fresh isolated workers per run"))),
)


def scripts() -> dict[str, Study]:
    """Every script of the suite, with the study it belongs to, in the pages' order."""
    return {script: study for study in STUDIES for script in study.scripts}


def is_envelope(doc: Any) -> bool:
    """Whether ``doc`` is a run in the common envelope (not a payload of an older run)."""
    return isinstance(doc, dict) and str(doc.get("format", "")).startswith("streamsvd-bench/")


def read_payload(path: str | Path) -> Any:
    """The study's own numbers in the JSON at ``path``, enveloped or not."""
    doc = json.loads(Path(path).read_text())
    return doc["results"] if is_envelope(doc) else doc


@dataclass(frozen=True)
class RunRecord:
    """One results file as the pages show it: when, where, on what, and its numbers."""

    path: Path
    enveloped: bool
    date: str | None
    cpu: str | None
    cores: int | None
    load_before: float | None
    load_after: float | None
    commit: str | None
    results: Any


def _first(*values: Any) -> Any:
    return next((v for v in values if v is not None), None)


def _load1(value: Any) -> float | None:
    """The one-minute figure of a load average (a list of three, or one number)."""
    while isinstance(value, list | tuple) and value:
        value = value[0]
    return float(value) if isinstance(value, int | float) else None


def read_run(path: str | Path) -> RunRecord:
    """Read a results file: the envelope, or the payload alone of an older run.

    For an older run the machine and load averages come from the keys the scripts used
    before the envelope (``machine.load_average``, ``load_average_before``, ``load_start``,
    ...); it has no date or commit.
    """
    path = Path(path)
    doc = json.loads(path.read_text())
    if is_envelope(doc):
        m, git = doc.get("machine") or {}, doc.get("git") or {}
        return RunRecord(path, True, doc.get("date"), m.get("cpu_model"), m.get("cpu_count"),
                         _load1(m.get("load_before")), _load1(m.get("load_after")),
                         git.get("commit"), doc.get("results"))
    d = doc if isinstance(doc, dict) else {}
    m = d.get("machine") if isinstance(d.get("machine"), dict) else {}
    load = d.get("load_average") if isinstance(d.get("load_average"), dict) else {}
    before = _first(d.get("load_average_before"), d.get("load_start"), load.get("start"),
                    m.get("load_average"), d.get("load"))
    after = _first(d.get("load_average_after"), d.get("load_end"), d.get("load_after"),
                   load.get("end"), m.get("load_average_after"), m.get("load_average_end"))
    return RunRecord(path, False, None, m.get("cpu_model"), m.get("cpu_count"),
                     _load1(before), _load1(after), None, doc)


def _scalars(d: Any) -> dict[str, Any]:
    return {k: v for k, v in d.items() if not isinstance(v, dict | list)} \
        if isinstance(d, dict) else {}


def _step(ctx: dict[str, Any], value: Any, segment: str) -> Iterator[tuple[dict, Any]]:
    if segment.startswith("*"):
        label = segment[1:]
        items = value.items() if isinstance(value, dict) else \
            enumerate(value) if isinstance(value, list) else ()
        for key, item in items:
            yield {**ctx, **_scalars(item), label: key}, item
    elif isinstance(value, list):
        for item in value:
            yield from _step({**ctx, **_scalars(item)}, item, segment)
    elif isinstance(value, dict) and segment in value:
        yield {**ctx, **_scalars(value)}, value[segment]


def table_rows(payload: Any, rows: str) -> list[dict[str, Any]]:
    """The rows that the path ``rows`` of a :class:`Table` reaches in ``payload``."""
    states: list[tuple[dict[str, Any], Any]] = [({}, payload)]
    for segment in (s for s in rows.split("/") if s):
        states = [nxt for ctx, value in states for nxt in _step(ctx, value, segment)]
    out = []
    for ctx, value in states:
        for item in value if isinstance(value, list) else [value]:
            out.append({**ctx, **item} if isinstance(item, dict) else {**ctx, "value": item})
    return out


def cell(row: dict[str, Any], column: Column) -> str:
    """The text of one cell: the value at ``column.key``, scaled and formatted."""
    value: Any = row
    for part in column.key.split("/"):
        value = value.get(part) if isinstance(value, dict) else None
    if value is None:
        return "–"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int | float):
        x = value * column.scale if column.scale != 1.0 else value
        return format(x, column.fmt) if column.fmt else str(x)
    return str(value).replace("|", "\\|")
