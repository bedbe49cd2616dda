"""The benchmark pages, rendered from each study's text and the files of ``bench/results``.

A study's page is its text (``bench/studies/NAME.md``) followed by what its results
files hold: the headline table of its latest results file (where :mod:`_suite` says how
to tabulate it), the list of its runs (file, date, machine, load, commit) and its figures.
The index page is ``bench/studies/index.md`` followed by the table of the studies.

``mkdocs.yml`` names this file as a hook: at each build, :func:`on_files` adds the pages
as ``benchmarks/*.md`` (they exist nowhere else), so the site shows the results found in
``bench/results`` at build time. ``python -m bench pages [--out DIR]`` writes the same
Markdown to ``DIR`` (default ``build/bench-pages``) to read it without building the site.
This module uses the standard library only (and mkdocs in :func:`on_files`).
"""

from __future__ import annotations

import argparse
import logging
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from _suite import (
    BENCH_DIR,
    RESULTS_DIR,
    STUDIES,
    STUDIES_DIR,
    RunRecord,
    Study,
    Table,
    cell,
    read_run,
    table_rows,
)

logger = logging.getLogger(__name__)

DOCS_FIGURES = "../bench/results"  # bench/results seen from docs/benchmarks/ (a symlink)
SITE_DIR = "benchmarks"


def _markdown_table(headers: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    lines = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def _date(run: RunRecord) -> str:
    return run.date.replace("T", " ")[:16] + " UTC" if run.date else "–"


def _load(x: float | None) -> str:
    return "–" if x is None else f"{x:.1f}"


def _read(path: Path) -> RunRecord | None:
    try:
        return read_run(path)
    except (OSError, ValueError) as exc:  # a file being written, or not JSON
        logger.warning("bench pages: %s is skipped (%s)", path, exc)
        return None


def _runs(study: Study, results: Path) -> list[RunRecord]:
    return [r for r in map(_read, study.result_files(".json", results)) if r is not None]


def _loads(run: RunRecord) -> str:
    before, after = run.load_before, run.load_after
    if before is None and after is None:
        return "load average not recorded"
    if after is None:
        return f"load average {_load(before)} at the start"
    if before is None:
        return f"load average {_load(after)} at the end"
    return f"load average {_load(before)} to {_load(after)}"


def describe(run: RunRecord) -> str:
    """One line on where and when a results file was measured."""
    if not run.enveloped:
        where = f" on {run.cpu} ({run.cores} cores)" if run.cpu else ""
        return (f"written before the suite's envelope{where}, {_loads(run)}; "
                "its date is in the study's text")
    commit = f", commit `{run.commit[:10]}`" if run.commit else ""
    return f"run of {_date(run)} on {run.cpu} ({run.cores} cores), {_loads(run)}{commit}"


def render_table(spec: Table, run: RunRecord) -> str:
    """The Markdown table of ``spec`` over the numbers of ``run``."""
    rows = table_rows(run.results, spec.rows)
    body = [[cell(row, c) for c in spec.columns] for row in rows]
    title = f"{spec.title}: " if spec.title else ""
    return (f"{title}`{spec.source}`, {describe(run)}.\n\n"
            + _markdown_table([c.header for c in spec.columns], body))


def render_page(study: Study, *, results: Path = RESULTS_DIR,
                figures: str = DOCS_FIGURES) -> str:
    """The page of ``study``: its text, its latest numbers, its runs and its figures.

    ``figures`` is the address of ``results`` as seen from the page.
    """
    parts = [study.prose.read_text().rstrip()]
    runs = _runs(study, results)
    by_name = {r.path.relative_to(results).as_posix(): r for r in runs}
    tables = [render_table(t, by_name[t.source]) for t in study.tables if t.source in by_name]
    if tables:
        parts.append("## Latest results\n\nGenerated from the results file that a run "
                     "with the default options writes.\n\n" + "\n\n".join(tables))
    if runs:
        rows = [[f"`{name}`", _date(r), r.cpu or "–", str(r.cores or "–"),
                 _load(r.load_before), _load(r.load_after),
                 f"`{r.commit[:10]}`" if r.commit else "–"] for name, r in by_name.items()]
        parts.append("## Runs recorded\n\nThe JSON files of this study in `bench/results/` "
                     "(load averages over one minute; files without a date were written "
                     "before the suite's envelope).\n\n" + _markdown_table(
                         ["file", "date", "CPU", "cores", "load before", "load after",
                          "commit"], rows))
    pngs = [p.relative_to(results).as_posix() for p in study.result_files(".png", results)]
    shown = [f for f in study.shown if (results / f).is_file()]
    if shown or pngs:
        lines = [f"![{f}]({figures}/{f})\n" for f in shown]
        lines += [f"* [`{f}`]({figures}/{f})" for f in pngs if f not in shown]
        parts.append("## Figures\n\n" + "\n".join(lines).rstrip() + "\n\nThe JSON beside "
                     "each figure in `bench/results/` holds every number of the run.")
    return "\n\n".join(parts) + "\n"


def render_index(*, results: Path = RESULTS_DIR) -> str:
    """The index page: ``bench/studies/index.md`` and the table of the studies."""
    rows = []
    for study in STUDIES:
        runs = _runs(study, results)
        dates = sorted(r.date for r in runs if r.date)
        rows.append([f"[{study.title}]({study.name}.md)",
                     ", ".join(f"`{s}.py`" for s in study.scripts), str(len(runs)),
                     _date(next(r for r in runs if r.date == dates[-1])) if dates else "–"])
    table = _markdown_table(["study", "scripts", "results files", "latest dated run"], rows)
    return ((STUDIES_DIR / "index.md").read_text().rstrip() + "\n\n## The studies\n\n"
            + table + "\n")


def pages(*, results: Path = RESULTS_DIR, figures: str = DOCS_FIGURES) -> dict[str, str]:
    """Every page, by file name: ``index.md`` and one ``NAME.md`` per study."""
    out = {"index.md": render_index(results=results)}
    for study in STUDIES:
        out[f"{study.name}.md"] = render_page(study, results=results, figures=figures)
    return out


def on_files(files: Any, config: Any) -> Any:
    """The mkdocs hook: add the pages to the site as ``benchmarks/*.md``."""
    from mkdocs.exceptions import PluginError
    from mkdocs.structure.files import File

    for name, content in pages().items():
        uri = f"{SITE_DIR}/{name}"
        if files.get_file_from_path(uri) is not None:
            raise PluginError(f"docs/{uri} exists, but the benchmark pages are generated from "
                              "bench/studies and bench/results: remove it")
        files.append(File.generated(config, uri, content=content))
    return files


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m bench pages``: write the pages to a directory."""
    p = argparse.ArgumentParser(prog="python -m bench pages",
                                description="Render the benchmark pages as Markdown.")
    p.add_argument("--out", default=str(BENCH_DIR.parent / "build" / "bench-pages"),
                   help="directory for the pages (default build/bench-pages)")
    p.add_argument("--results", default=str(RESULTS_DIR),
                   help="the results directory to read (default bench/results)")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    out, results = Path(args.out), Path(args.results).resolve()
    out.mkdir(parents=True, exist_ok=True)
    figures = Path(os.path.relpath(results, out.resolve())).as_posix()
    written = pages(results=results, figures=figures)
    for name, content in written.items():
        (out / name).write_text(content)
    logger.info("wrote %d pages to %s", len(written), out)
    return 0
