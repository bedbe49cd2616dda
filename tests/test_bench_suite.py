"""The benchmark suite: the runner, the results envelope, the pages and the list of studies."""

import ast
import importlib
import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "bench"

TINY_STUDY = '''
import argparse
from pathlib import Path

from _common import Run


def main(argv=None):
    record = Run("tiny_study", argv)
    p = argparse.ArgumentParser()
    p.add_argument("--out")
    p.add_argument("--n", type=int, default=3)
    args = p.parse_args(argv)
    payload = {"n": args.n, "rows": [{"name": f"r{i}", "value": i / 3} for i in range(args.n)]}
    out = Path(args.out)
    (out / "tiny_study.png").write_bytes(b"png")
    (out / "tiny_study_more.png").write_bytes(b"png")
    record.write(out / "tiny_study.json", payload)
    return payload
'''


@pytest.fixture
def suite(monkeypatch, tmp_path):
    """The suite's modules with one more study, ``tiny``, whose script and record are in
    ``tmp_path``; its results go to ``tmp_path / "results"``."""
    monkeypatch.syspath_prepend(str(BENCH))
    monkeypatch.syspath_prepend(str(tmp_path))
    (tmp_path / "tiny_study.py").write_text(TINY_STUDY)
    (tmp_path / "studies").mkdir()
    (tmp_path / "studies" / "tiny.md").write_text("# Tiny\n\nWhat the tiny study measures.\n")
    (tmp_path / "studies" / "index.md").write_text("# Benchmarks\n")
    (tmp_path / "results").mkdir()
    _suite = importlib.import_module("_suite")
    tiny = _suite.Study("tiny", "Tiny", ("tiny_study",), shown=("tiny_study.png",),
                        files=("tiny_study*",), tables=(_suite.table("tiny_study.json", "rows", [
                            ("name", "name"), ("value", "value", ".2f"), ("x 10", "value", ".1f", 10),
                            ("absent", "nothing")]),))
    monkeypatch.setattr(_suite, "STUDIES", (*_suite.STUDIES, tiny))
    monkeypatch.setattr(_suite, "STUDIES_DIR", tmp_path / "studies")
    spec = importlib.util.spec_from_file_location("bench_runner", BENCH / "__main__.py")
    runner = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(runner)
    monkeypatch.setattr(runner, "STUDIES", _suite.STUDIES)
    pages = importlib.import_module("_pages")
    monkeypatch.setattr(pages, "STUDIES", (tiny,))  # the others' records are not in tmp_path
    monkeypatch.setattr(pages, "STUDIES_DIR", tmp_path / "studies")
    monkeypatch.setattr(sys, "argv", list(sys.argv))  # the runner names the program there
    return _suite, runner, pages, tiny


def test_list_names_every_script():
    done = subprocess.run([sys.executable, "-m", "bench", "--list"], cwd=ROOT,
                          capture_output=True, text=True, check=True)
    lines = done.stdout.splitlines()
    sys.path.insert(0, str(BENCH))
    try:
        scripts = importlib.import_module("_suite").scripts()
    finally:
        sys.path.remove(str(BENCH))
    assert [ln.split()[0] for ln in lines] == list(scripts)
    assert all(len(ln.split(maxsplit=2)) == 3 for ln in lines)  # name, [study], summary
    bad = subprocess.run([sys.executable, "-m", "bench", "no_such_study"], cwd=ROOT,
                         capture_output=True, text=True)
    assert bad.returncode == 2 and "--list" in bad.stderr


def test_runner_writes_the_envelope_and_the_page_shows_it(suite, tmp_path):
    _suite, runner, pages, tiny = suite
    results = tmp_path / "results"
    argv = ["--out", str(results), "--n", "4"]
    assert runner.resolve("tiny-study.py") == "tiny_study" == runner.resolve("tiny")
    assert runner.main(["tiny_study", *argv]) == 0

    doc = json.loads((results / "tiny_study.json").read_text())
    assert doc["format"] == _suite.FORMAT and doc["study"] == "tiny_study"
    assert doc["argv"] == argv and doc["date"].endswith("+00:00") and doc["seconds"] >= 0
    machine = doc["machine"]
    assert machine["cpu_count"] >= 1 and "cpu_model" in machine
    assert len(machine["load_before"]) == len(machine["load_after"]) == 3
    assert doc["versions"]["numpy"] and doc["versions"]["python"]
    assert doc["git"] is None or len(doc["git"]["commit"]) == 40
    assert doc["results"]["n"] == 4 and _suite.read_payload(results / "tiny_study.json") == \
        doc["results"]

    # a file of a run from before the envelope: the payload alone
    old = {"rows": [{"name": "old", "value": 1.0}],
           "machine": {"cpu_model": "Old CPU", "cpu_count": 2, "load_average": [1.5, 1, 1]}}
    (results / "tiny_study_old.json").write_text(json.dumps(old))
    assert _suite.read_payload(results / "tiny_study_old.json") == old
    run = _suite.read_run(results / "tiny_study_old.json")
    assert not run.enveloped and run.date is None and run.load_before == 1.5
    assert run.cpu == "Old CPU" and run.results == old

    page = pages.render_page(tiny, results=results, figures="FIG")
    assert page.startswith("# Tiny\n\nWhat the tiny study measures.\n")
    assert "## Latest results" in page and "`tiny_study.json`, run of " in page
    assert "| name | value | x 10 | absent |" in page
    assert "| r3 | 1.00 | 10.0 | – |" in page and "| old |" not in page
    runs = page[page.index("## Runs recorded"):page.index("## Figures")]
    assert "| `tiny_study.json` | 20" in runs and "| `tiny_study_old.json` | – | Old CPU | 2 | 1.5 |" in runs
    figures = page[page.index("## Figures"):]
    assert "![tiny_study.png](FIG/tiny_study.png)" in figures
    assert "* [`tiny_study_more.png`](FIG/tiny_study_more.png)" in figures

    out = tmp_path / "pages"
    assert pages.main(["--out", str(out), "--results", str(results)]) == 0
    assert (out / "tiny.md").read_text() == pages.render_page(
        tiny, results=results, figures="../results")
    assert "| [Tiny](tiny.md) | `tiny_study.py` | 2 | 20" in (out / "index.md").read_text()


def test_table_rows_follow_lists_and_mappings():
    sys.path.insert(0, str(BENCH))
    try:
        _suite = importlib.import_module("_suite")
    finally:
        sys.path.remove(str(BENCH))
    payload = {"rank": 3, "cases": [{"n": 10, "runs": [{"method": "a"}, {"method": "b"}]},
                                    {"n": 20, "runs": [{"method": "c"}]}],
               "by": {"x": {"t": {"s": 1}, "u": {"s": 2}}}}
    assert [(r["rank"], r["n"], r["method"]) for r in _suite.table_rows(payload, "cases/runs")] \
        == [(3, 10, "a"), (3, 10, "b"), (3, 20, "c")]
    rows = _suite.table_rows(payload, "by/*case/*run")
    assert [(r["case"], r["run"], r["s"]) for r in rows] == [("x", "t", 1), ("x", "u", 2)]
    col = _suite.Column("s", "by/x/u/s", ".1f", 10)
    assert _suite.cell(payload, col) == "20.0"
    assert _suite.table_rows(payload, "missing") == []


def test_every_study_has_its_scripts_record_page_and_index_entry():
    sys.path.insert(0, str(BENCH))
    try:
        _suite = importlib.import_module("_suite")
    finally:
        sys.path.remove(str(BENCH))
    nav = (ROOT / "mkdocs.yml").read_text()
    readme = (BENCH / "README.md").read_text()
    with_main = {p.stem for p in BENCH.glob("*.py") if any(
        isinstance(node, ast.FunctionDef) and node.name == "main"
        for node in ast.parse(p.read_text()).body) and not p.stem.startswith("_")}
    assert set(_suite.scripts()) == with_main
    for study in _suite.STUDIES:
        assert study.prose.read_text().startswith("# "), study.name
        assert f"benchmarks/{study.name}.md" in nav, study.name
        assert f"(studies/{study.name}.md)" in readme, study.name
        for figure in study.shown:
            assert (_suite.RESULTS_DIR / figure).is_file(), figure
        for spec in study.tables:
            if (_suite.RESULTS_DIR / spec.source).is_file():
                rows = _suite.table_rows(_suite.read_payload(_suite.RESULTS_DIR / spec.source),
                                         spec.rows)
                assert rows, (study.name, spec.source)
                assert any(_suite.cell(r, c) != "–" for r in rows for c in spec.columns[1:])
