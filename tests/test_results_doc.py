"""docs/results.md is generated from bench-results/*.json (haa/lab/results/, `make results`): the committed page
must be what the JSON files give, every file must have its section, and a changed number must change the page."""

from __future__ import annotations

import json
import shutil

import pytest

from haa.lab import results

RESULT_FILES = sorted(results.RESULTS_DIR.glob("*.json"))


def test_the_committed_page_is_what_the_json_files_give():
    assert results.PAGE.read_text() == results.generate(results.RESULTS_DIR), (
        "docs/results.md is stale: a bench-results/*.json changed; run `make results` and commit the page")


@pytest.mark.parametrize("path", RESULT_FILES, ids=[p.stem for p in RESULT_FILES])
def test_every_result_file_has_a_section(path):
    page = results.PAGE.read_text()
    assert f"Source: `bench-results/{path.name}`" in page


def test_a_changed_number_changes_the_page_and_fails_the_check(tmp_path, capsys):
    data = tmp_path / "bench-results"
    shutil.copytree(results.RESULTS_DIR, data)
    page = tmp_path / "results.md"
    assert results.main(["--results", str(data), "--out", str(page)]) == 0
    assert results.main(["--check", "--results", str(data), "--out", str(page)]) == 0
    before = page.read_text()

    ap1 = json.loads((data / "ap1.json").read_text())
    ap1["rows"][0]["throughput_tx_per_s"] = 98765.4
    (data / "ap1.json").write_text(json.dumps(ap1))
    after = results.generate(data)
    assert after != before
    assert "98,765" in after and "98,765" not in before

    capsys.readouterr()
    assert results.main(["--check", "--results", str(data), "--out", str(page)]) == 1
    assert "make results" in capsys.readouterr().err


def test_an_unknown_file_gets_a_generic_section(tmp_path):
    data = tmp_path / "bench-results"
    data.mkdir()
    (data / "newbench.json").write_text(json.dumps({"what": "a new benchmark", "ops_per_s": 4321.5, "rows": [1, 2]}))
    page = results.generate(data)
    assert "Source: `bench-results/newbench.json`" in page
    assert "4,322" in page and "`rows` (list of 2)" in page
