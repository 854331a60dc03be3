"""A run's memory estimate and limit: sizes parsed, the limit's source, a clear error before decoding."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from pmvir.config import PipelineConfig
from pmvir.errors import ConfigError, ResourceLimitError
from pmvir.memory import check_memory, estimated_peak_bytes, mapped_overhead_bytes, memory_limit, parse_bytes
from pmvir.pipeline import run
from pmvir.synth import synthesize


@pytest.mark.parametrize(
    ("text", "value"),
    [("12G", 12 * 2**30), ("800M", 800 * 2**20), ("12GiB", 12 * 2**30), ("1.5g", int(1.5 * 2**30)), ("4096", 4096)],
)
def test_sizes_parse_in_powers_of_1024(text: str, value: int) -> None:
    assert parse_bytes(text) == value


@pytest.mark.parametrize("text", ["", "twelve", "-1G", "12X", "0"])
def test_bad_sizes_are_config_errors(text: str) -> None:
    with pytest.raises(ConfigError, match="memory size"):
        parse_bytes(text)


def test_the_limit_comes_from_the_argument_then_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("PMVIR_JOB_MEMORY", raising=False)
    assert memory_limit() == (None, "")
    monkeypatch.setenv("PMVIR_JOB_MEMORY", "0")
    assert memory_limit() == (None, "")
    monkeypatch.setenv("PMVIR_JOB_MEMORY", "8G")
    assert memory_limit() == (8 * 2**30, "PMVIR_JOB_MEMORY")
    assert memory_limit(2**30) == (2**30, "--max-memory")


def test_binning_lowers_the_estimate_and_the_error_says_what_fits() -> None:
    full = estimated_peak_bytes((2448, 2048), 36, 1)
    binned = estimated_peak_bytes((2448, 2048), 36, 3)
    assert binned < full / 4
    assert check_memory("cap", (2448, 2048), 36, 3, None, "") == binned
    with pytest.raises(ResourceLimitError) as err:
        check_memory("cap", (2448, 2048), 36, 1, binned + 2**20, "PMVIR_JOB_MEMORY")
    message = str(err.value)
    assert message.startswith("cap: 36 frames of 2448x2048")
    assert "PMVIR_JOB_MEMORY" in message and "decode.max_working_size_px=" in message
    suggested = int(message.split("decode.max_working_size_px=")[1].split(" ")[0])
    factor = -(-2448 // suggested)
    assert estimated_peak_bytes((2448, 2048), 36, factor) <= binned + 2**20


def test_a_decode_only_run_is_estimated_at_full_size_without_the_refinement() -> None:
    """Decoding alone keeps 36 full-size views (about 8 GiB), far below the refinement's model at full
    size (84 GiB), so a 12 GiB worker takes it; over a limit it names how many views fit, not binning."""
    decode = estimated_peak_bytes((2448, 2048), 36, 1, decode_only=True)
    assert 7 * 2**30 < decode < 9 * 2**30 < estimated_peak_bytes((2448, 2048), 36, 1)
    assert check_memory("cap", (2448, 2048), 36, 1, 12 * 2**30, "PMVIR_JOB_MEMORY", decode_only=True) == decode
    with pytest.raises(ResourceLimitError) as err:
        check_memory("cap", (2448, 2048), 36, 1, 4 * 2**30, "PMVIR_JOB_MEMORY", decode_only=True)
    message = str(err.value)
    assert "decode.max_working_size_px" not in message
    views = int(message.split("at most ")[1].split(" views")[0])
    assert estimated_peak_bytes((2448, 2048), views, 1, decode_only=True) <= 4 * 2**30
    assert estimated_peak_bytes((2448, 2048), views + 1, 1, decode_only=True) > 4 * 2**30


def test_under_an_address_space_cap_the_mapped_overhead_counts() -> None:
    """A service worker caps a job's address space (RLIMIT_AS) at PMVIR_JOB_MEMORY; the libraries a
    process maps (torch, Open3D, pycolmap: gigabytes of address space, little of it resident) take
    part of that, so the check reserves it. Without a cap nothing is reserved."""
    code = (
        "import json, resource; import torch, open3d; from pmvir.memory import mapped_overhead_bytes as m; "
        "before = m(); resource.setrlimit(resource.RLIMIT_AS, (64 * 2**30, resource.getrlimit(resource.RLIMIT_AS)[1])); "
        "print(json.dumps([before, m()]))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    before, capped = json.loads(out.stdout)
    assert before == 0 and 2**28 < capped < 64 * 2**30, (before, capped)
    assert mapped_overhead_bytes() >= 0
    need = estimated_peak_bytes((2448, 2048), 36, 3)
    assert check_memory("cap", (2448, 2048), 36, 3, need + 2**30, "PMVIR_JOB_MEMORY", reserved=2**29) == need
    with pytest.raises(ResourceLimitError, match=r"plus 2\.0 GiB of address space the process maps already"):
        check_memory("cap", (2448, 2048), 36, 3, need + 2**30, "PMVIR_JOB_MEMORY", reserved=2 * 2**30)


def test_a_capture_over_the_limit_fails_before_decoding(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    capture = synthesize(tmp_path / "cap", shape="sphere", views=3, size=(64, 48), seed=0)
    monkeypatch.setenv("PMVIR_JOB_MEMORY", "256M")
    with pytest.raises(ResourceLimitError, match=r"0\.2 GiB \(PMVIR_JOB_MEMORY\)"):
        run(PipelineConfig(), capture, tmp_path / "out")
    assert not (tmp_path / "out" / "report.json").exists()
    proc = subprocess.run(
        [sys.executable, "-m", "pmvir.cli", "reconstruct", str(capture), "--out", str(tmp_path / "o2"),
         "--max-memory", "300M", "--quiet"],
        capture_output=True, text=True, check=False,
        env={k: v for k, v in os.environ.items() if k != "PMVIR_JOB_MEMORY"},
    )
    assert proc.returncode != 0
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "--max-memory" in lines[0] and "0.3 GiB" in lines[0], proc.stderr


def test_the_estimate_covers_the_measured_peaks() -> None:
    results = Path(__file__).resolve().parents[1] / "bench" / "results" / "fullsize.json"
    if not results.is_file():
        pytest.skip("no stored bench/fullsize.py result")
    runs = [r for r in json.loads(results.read_text())["runs"] if "error" not in r]
    assert runs
    for r in runs:
        w, h = (int(x) for x in r["size"].split("x"))
        estimate = estimated_peak_bytes((w, h), r["views"], r["resolution"]["binning"])
        measured = r["peak_rss_gib"] * 2**30
        # the stored runs may use a coarser subdivision than the defaults the estimate is for
        assert measured <= estimate <= 3 * measured, (r["size"], estimate / 2**30, r["peak_rss_gib"])
