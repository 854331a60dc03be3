"""The service's pure pieces: path rules, Range parsing, keys, settings, result publishing."""

from __future__ import annotations

import json
import re
import zipfile
from pathlib import Path

import pytest
from pydantic import ValidationError

from service.errors import ApiError
from service.keys import hash_entry, parse_entry, plain_tenant
from service.ranges import parse_range
from service.routes_files import CAPTURE_PATH_PATTERN
from service.settings import Settings
from service.storage import JobFiles, capture_path_problem, write_result_zip
from service.uploads import parse_content_range

GOOD_PATHS = [
    "capture.json",
    "frames/000.png",
    "frames/view_01.TIFF",
    "frames/a.b-c+d.dng",
    "frames/x.raw",
    "frames/x.bin",
    "frames/x.tif",
    "masks/000.png",
    "gt/mesh.ply",
    "gt/illumination.json",
]
BAD_PATHS = {
    "": "is empty",
    "../capture.json": "path traversal",
    "frames/../capture.json": "path traversal",
    "frames//000.png": "path traversal",
    "./capture.json": "path traversal",
    "/capture.json": "absolute path",
    "C:/frames/000.png": "absolute path",
    "frames\\000.png": "backslash",
    "frames/0\x00.png": "NUL",
    "frames/sub/000.png": "capture layout",
    "gt/other.ply": "capture layout",
    "capture.json.bak": "capture layout",
    "frames/000.jpg": "must end in one of",
    "frames/.png": "must end in one of",
    "masks/000.tif": "must end in one of",
    "frames/.hidden.png": "unsupported file name",
    "frames/a b.png": "unsupported file name",
    "frames/" + "x" * 129 + ".png": "unsupported file name",
}


@pytest.mark.parametrize("path", GOOD_PATHS)
def test_capture_layout_paths_are_accepted(path: str) -> None:
    assert capture_path_problem(path) is None
    assert re.match(CAPTURE_PATH_PATTERN, path), "the documented pattern must accept it too"


@pytest.mark.parametrize("path, problem", BAD_PATHS.items())
def test_paths_outside_the_layout_are_named(path: str, problem: str) -> None:
    found = capture_path_problem(path)
    assert found is not None and problem in found
    assert not re.match(CAPTURE_PATH_PATTERN, path), "the documented pattern must reject it too"


@pytest.mark.parametrize(
    "header, size, expected",
    [
        (None, 100, None),
        ("bytes=0-9", 100, (0, 9)),
        ("bytes=90-", 100, (90, 99)),
        ("bytes=95-200", 100, (95, 99)),
        ("bytes=-10", 100, (90, 99)),
        ("bytes=-500", 100, (0, 99)),
        ("bytes=100-", 100, "unsatisfiable"),
        ("bytes=-0", 100, "unsatisfiable"),
        ("bytes=5-2", 100, None),  # invalid: ignored, the whole file is sent
        ("bytes=0-1,5-6", 100, None),  # several ranges: the whole file
        ("items=0-9", 100, None),  # another unit: ignored
        ("bytes=abc", 100, None),
        ("bytes=-", 100, None),
        ("bytes=0-", 0, "unsatisfiable"),
    ],
)
def test_range_header_parsing(header: str | None, size: int, expected: object) -> None:
    assert parse_range(header, size) == expected


def test_content_range_parsing() -> None:
    r = parse_content_range("bytes 100-199/1000")
    assert (r.first, r.last, r.total) == (100, 199, 1000)
    for bad in ("bytes 5-2/10", "bytes 0-10/10", "bytes */10", "bytes 0-9/*", "0-9/10", "bytes 0-9"):
        with pytest.raises(ApiError) as err:
            parse_content_range(bad)
        assert err.value.status == 400


def test_keys_plain_and_hashed_several_per_tenant_and_admins() -> None:
    rotated, current = "lab-a-key-2025-old", "lab-a-key-2026-new"
    s = Settings(
        api_keys=f"alpha, {hash_entry('lab-a', rotated)} ,,{hash_entry('lab-a', current)}",
        admin_keys=hash_entry("ops", "operator-key-0001"),
    )
    ring = s.keyring
    assert ring.tenant("alpha") == plain_tenant("alpha") and "alpha" not in ring.tenant("alpha")
    assert ring.tenant(rotated) == ring.tenant(current) == "lab-a"  # rotation keeps the tenant's jobs
    assert ring.tenant("operator-key-0001") == "ops" and ring.admins == {"ops"}
    for wrong in ("", "alph", "alphaa", "ALPHA", " alpha", rotated + "x"):
        assert ring.tenant(wrong) is None
    assert ring.tenant(current) == "lab-a"  # answered from the cache the second time
    assert all(current not in e and rotated not in e for e in s.api_keys)  # only hashes are configured
    with pytest.raises(ValueError, match="tenant"):
        parse_entry("bad tenant=scrypt:" + "00" * 16 + ":" + "ab" * 32)


def test_settings_from_environment(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv("PMVIR_REDIS_URL", "redis://example:6380/2")
    monkeypatch.setenv("PMVIR_STORAGE", str(tmp_path))
    monkeypatch.setenv("PMVIR_API_KEYS", "k1,k2")
    monkeypatch.setenv("PMVIR_MAX_FRAMES", "12")
    s = Settings()
    assert (s.redis_url, s.storage, s.api_keys, s.max_frames) == (
        "redis://example:6380/2",
        tmp_path,
        ("k1", "k2"),
        12,
    )


def test_settings_refuse_a_visibility_timeout_shorter_than_the_longest_job() -> None:
    with pytest.raises(ValidationError, match="visibility_timeout"):
        Settings(job_soft_time_limit=100, job_hard_time_limit=200, visibility_timeout=150)
    with pytest.raises(ValidationError, match="job_hard_time_limit"):
        Settings(job_soft_time_limit=100, job_hard_time_limit=100, visibility_timeout=1000)
    with pytest.raises(ValidationError):
        Settings(max_frames=0)


def test_publishing_a_result_twice_replaces_it_whole(tmp_path: Path) -> None:
    files = JobFiles(tmp_path)
    for attempt, text in enumerate(("first", "second")):
        run = files.run_dir("j1", f"run{attempt}")
        (run / "decoded").mkdir(parents=True)
        (run / "report.json").write_text(json.dumps({"run": text}))
        (run / "decoded" / "000.npz").write_bytes(b"\0" * 1000)
        if attempt == 0:
            (run / "only-first.txt").write_text("x")
        files.publish_result("j1", run)
        assert not run.exists()
    result = files.result_dir("j1")
    assert json.loads((result / "report.json").read_text()) == {"run": "second"}
    assert not (result / "only-first.txt").exists()
    with zipfile.ZipFile(result / "result.zip") as zf:
        assert sorted(zf.namelist()) == ["decoded/000.npz", "report.json"]
        assert zf.getinfo("decoded/000.npz").compress_type == zipfile.ZIP_STORED
        assert zf.getinfo("report.json").compress_type == zipfile.ZIP_DEFLATED
    assert files.result_file("j1", "report.json") == result / "report.json"
    assert files.result_file("j1", "mesh.ply") is None
    assert files.result_file("j1", "../capture.json") is None


def test_result_zip_leaves_no_temporary_file(tmp_path: Path) -> None:
    (tmp_path / "a.json").write_text("{}")
    write_result_zip(tmp_path)
    write_result_zip(tmp_path)  # again: result.zip itself is not zipped into the new one
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.json", "result.zip"]
    with zipfile.ZipFile(tmp_path / "result.zip") as zf:
        assert zf.namelist() == ["a.json"]


def test_the_api_checks_a_jobs_stages_without_loading_the_library() -> None:
    """Starting a job checks its stop_after; that must not import the pipeline (torch, Open3D, pycolmap)
    into the API process, which took 3 s on each API process's first start."""
    import subprocess
    import sys

    code = (
        "import sys, types\n"
        "import service.app\n"
        "from service.jobs import stage_problems\n"
        "assert stage_problems(types.SimpleNamespace(options={'stop_after': 'refine'})) == []\n"
        "print(sorted(m for m in ('pmvir.pipeline', 'torch', 'open3d', 'pycolmap') if m in sys.modules))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120)
    assert out.stdout.strip() == "[]", out.stdout
