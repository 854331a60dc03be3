"""docs/benchmarks.md is what bench/report.py writes from bench/results/*.json (no number typed by hand)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "benchmarks.md"
RESULTS = ROOT / "bench" / "results"


def test_the_benchmarks_page_equals_the_generated_one(tmp_path: Path) -> None:
    out = tmp_path / "benchmarks.md"
    subprocess.run(
        [sys.executable, str(ROOT / "bench" / "report.py"), "--out", str(out)], check=True, capture_output=True
    )
    assert PAGE.read_text() == out.read_text(), (
        "docs/benchmarks.md differs from bench/results/*.json: run .venv/bin/python bench/report.py"
    )


def test_every_stored_result_names_its_machine_date_and_command() -> None:
    for path in sorted(RESULTS.glob("*.json")):
        doc = json.loads(path.read_text())
        assert doc["benchmark"] == path.stem, path
        assert doc["measured_at"][:4].isdigit() and "T" in doc["measured_at"], path
        assert doc["command"].startswith(".venv/bin/python bench/"), path
        assert {"cpu_model", "cores", "memory_gib"} <= set(doc["machine"]), path
        assert doc["tables"] and all(t["rows"] for t in doc["tables"]), path


def test_a_benchmark_without_a_result_shows_its_command(tmp_path: Path) -> None:
    (tmp_path / "results").mkdir()
    doc = {
        "benchmark": "synth",
        "measured_at": "2000-01-01T00:00:00+00:00",
        "command": ".venv/bin/python bench/synth.py --views 3",
        "machine": {"cpu_model": "Test CPU", "cores": 4, "memory_gib": 8.0},
        "tables": [{"title": "T", "columns": ["a", "b"], "rows": [["x", 1234.5678]], "note": None}],
    }
    (tmp_path / "results" / "synth.json").write_text(json.dumps(doc))
    out = tmp_path / "page.md"
    subprocess.run(
        [sys.executable, str(ROOT / "bench" / "report.py"), "--results", str(tmp_path / "results"), "--out", str(out)],
        check=True,
        capture_output=True,
    )
    page = out.read_text()
    synth = page.split("## Synthetic captures")[1].split("\n## ")[0]
    assert "Test CPU, 4 cores, 8.0 GiB memory" in synth and "2000-01-01T00:00:00+00:00" in synth
    assert "`.venv/bin/python bench/synth.py --views 3`" in synth and "| x | 1,235 |" not in synth
    assert "| x | 1235 |" in synth  # four significant digits
    refine = page.split("## Refinement against ground truth")[1].split("\n## ")[0]
    assert "No current measurement is stored." in refine and ".venv/bin/python bench/refine.py" in refine
