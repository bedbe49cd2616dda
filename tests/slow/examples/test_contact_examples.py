import importlib
import json
import logging
import runpy
from pathlib import Path

import pytest

import contact
from contact.cli import main

ROOT = Path(__file__).resolve().parents[3]


def test_billet_example_runs_and_reproduces_the_paper_trends(tmp_path, capsys):
    script = runpy.run_path(str(ROOT / "examples" / "billet.py"))
    summary = script["main"](["--out", str(tmp_path), "--dt", "0.02", "--max-iter", "200"])
    for name in ("fig5_convergence", "fig6_svd", "fig7_space_modes", "fig8_mac_p3",
                 "fig9_mac_pgd"):
        assert (tmp_path / f"{name}.png").stat().st_size > 10_000
    on_disk = json.loads((tmp_path / "summary.json").read_text())
    assert on_disk["problem"]["instants"] == 51
    rows = {r["method"]: r for r in summary["table"]}
    assert rows["latin"]["converged"]
    assert rows["latin"]["error_u_vs_reference"] < 1e-4
    opt = rows["latin-pgd"]["optimal_svd_size"]
    assert abs(rows["latin-pgd"]["final_basis_size"] - opt) <= max(2, 0.1 * opt)
    assert rows["latin-p3"]["final_basis_size"] > opt
    assert summary["reference"]["laws_worst_violation"] < 1e-10
    capsys.readouterr()


def test_cli_writes_the_figures(tmp_path, capsys):
    out = tmp_path / "cli"
    code = main(["billet", "--out", str(out), "--dt", "0.05", "--max-iter", "60",
                 "--fine-trunc", "0", "--quiet"])
    assert code == 0
    assert (out / "fig5_convergence.png").exists()
    summary = json.loads((out / "summary.json").read_text())
    assert [r["method"] for r in summary["table"]] == ["latin", "latin-p3", "latin-pgd"]
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err == ""  # --quiet: no progress messages, no bars


def test_cli_reports_progress_on_stderr_and_the_table_on_stdout(tmp_path, capsys):
    handlers = list(logging.getLogger("contact").handlers)
    out = tmp_path / "cli"
    # no method reaches the level 1e-12: the table must say so, not print None
    code = main(["billet", "--out", str(out), "--dt", "0.05", "--max-iter", "60",
                 "--fine-trunc", "0", "--level", "1e-12", "--verbose"])
    assert code == 0
    captured = capsys.readouterr()
    assert logging.getLogger("contact").handlers == handlers  # nothing left behind
    # stdout: the table only
    assert "None" not in captured.out
    assert "INFO" not in captured.out and "it/s" not in captured.out
    rows = {line.split()[0]: line.split() for line in captured.out.splitlines()[2:5]}
    assert list(rows) == ["latin", "latin-p3", "latin-pgd"]
    assert all(r[2] == "never" and r[3] == "-" for r in rows.values())
    assert rows["latin"][4] == "full" and rows["latin-p3"][4].isdigit()
    assert "latin: basis 'full': no basis" in captured.out
    assert "latin-pgd: it@lvl 'never', cpu@lvl '-'" in captured.out
    # stderr: every stage, in order, then each file written
    stages = [
        "contact billet: writing Figs. 5-9 and summary.json into",
        "building the billet mesh",
        "billet: 368 dofs (318 free), 42 contact nodes, 21 instants",
        "reference solve: semi-smooth Newton",
        "reference solve: 21 instants",
        "latin: solving",
        "latin: global operator factorised",
        " iterations in ",
        "latin-p3: solving",
        "latin-p3: global operator factorised",
        "latin-pgd: solving",
        "latin-pgd: global operator factorised",
        "SVD of the reference correction",
    ] + [f"wrote {out / name}" for name in (
        "fig5_convergence.png", "fig6_svd.png", "fig7_space_modes.png", "fig8_mac_p3.png",
        "fig9_mac_pgd.png", "summary.json")]
    err = captured.err
    positions = [err.find(stage) for stage in stages]
    assert -1 not in positions, [s for s, p in zip(stages, positions, strict=True) if p < 0]
    assert positions == sorted(positions)
    assert "latin-pgd:" in err and "it/s" in err  # the progress bars
    assert "latin-pgd iteration 50: indicator" in err  # --verbose: DEBUG messages


def test_cli_reports_a_bad_option_as_an_error(tmp_path, capsys):
    assert main(["billet", "--out", str(tmp_path), "--dt", "0.3", "--quiet"]) == 2
    assert "`dt` must divide" in capsys.readouterr().err


def test_cli_requires_a_command():
    with pytest.raises(SystemExit):
        main([])


def test_scale_bench_runs_on_small_sizes(tmp_path, monkeypatch, capsys):
    monkeypatch.syspath_prepend(str(ROOT / "bench"))
    # imported (not run_path) so that its solves can run in spawned processes
    mod = importlib.import_module("bench_contact_scale")
    result = mod.main(["--quick", "--out", str(tmp_path), "--max-iter", "300"])
    for name in ("scale", "k", "cost"):
        assert (tmp_path / f"{name}.png").stat().st_size > 5_000
        assert json.loads((tmp_path / f"{name}.json").read_text())["results"]
    for row in result["scale"]:
        assert row["latin"]["converged"] and row["latin-p3"]["converged"]
        assert row["latin-pgd"]["representation_bytes"] < row["full_field_bytes"] * 1.05
        for key in ("reference", "latin", "latin-p3", "latin-pgd"):
            assert row[key]["peak_traced_bytes"] > 0
            assert row[key]["peak_rss_bytes"] >= row[key]["rss_before_bytes"] > 0
        sizes = row["optimal_svd_size"]["0.0001"]
        assert sizes["tail_energy"] >= sizes["sigma_ratio"] > 0
    cost = result["cost"]
    for method in ("latin-p3", "latin-pgd"):
        assert len(cost[method]["cpu_s"]) == len(cost[method]["basis_size"]) > 0
    phases = result["breakdown"]["latin-pgd"]["phases_s"]
    assert phases["StreamCompressor.add"] > 0 and phases["local stage"] > 0
    its = [r["iterations"] for r in result["k"]["rows"]]
    assert len(its) == 3 and all(i > 0 for i in its)
    capsys.readouterr()


def test_package_exposes_the_study_lazily():
    assert callable(contact.billet_study)
    with pytest.raises(AttributeError):
        contact.not_there  # noqa: B018


def test_subspace_bench_runs_on_a_small_size(tmp_path, monkeypatch, capsys):
    monkeypatch.syspath_prepend(str(ROOT / "bench"))
    mod = importlib.import_module("bench_contact_subspace")
    result = mod.main(["--quick", "--out", str(tmp_path)])
    assert (tmp_path / "subspace.png").stat().st_size > 5_000
    assert json.loads((tmp_path / "subspace.json").read_text())["results"]["fixed"]
    for row in result["fixed"]:
        assert 0 < row["min_indicator"] <= row["last_indicator"]
        assert row["truncated_reference"] > 0
    for row in result["pgd"]:
        assert row["optimal"]["tail_energy"] >= row["optimal"]["sigma_ratio"] > 0
        assert row["min_indicator"] > 0
    capsys.readouterr()
