"""A job's bounds (threads, memory) and the stage cache's signatures, in real processes and files."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from service import cache_sign, limits


def _run(code: str) -> dict:
    out = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True, timeout=120, check=True
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_apply_threads_bounds_torch_opencv_and_blas() -> None:
    seen = _run(
        """
        import json
        from service import limits
        seen = limits.apply_threads(2)
        from threadpoolctl import threadpool_info
        seen["pools"] = sorted({p["num_threads"] for p in threadpool_info()})
        print(json.dumps(seen))
        """
    )
    assert seen["torch"] == 2 and seen["opencv"] == 2
    assert seen["pools"] in ([2], [1, 2], [])  # every BLAS/OpenMP pool loaded is at most 2


def test_apply_threads_reaches_pycolmap_options() -> None:
    seen = _run(
        """
        import json
        from service import limits
        limits.apply_threads(3)
        from pmvir.config import SfmOptions
        from pmvir.geometry.sfm import colmap, matching
        options = SfmOptions()
        print(json.dumps({
            "threads": matching.colmap_threads(),
            "incremental": colmap._pipeline_options(options, set()).num_threads,
            "global": colmap._global_options(options, set()).num_threads,
        }))
        """
    )
    assert seen == {"threads": 3, "incremental": 3, "global": 3}


def test_memory_cap_turns_a_large_allocation_into_out_of_memory() -> None:
    seen = _run(
        """
        import json, resource
        import numpy as np
        from service import limits
        vsz = int(open("/proc/self/statm").read().split()[0]) * resource.getpagesize()
        limits.apply_memory(vsz + 256 * 2**20)
        try:
            np.ones(2**30, dtype=np.uint8)
            print(json.dumps({"oom": False}))
        except Exception as exc:
            print(json.dumps({"oom": limits.out_of_memory(exc), "type": type(exc).__name__}))
        """
    )
    assert seen == {"oom": True, "type": "MemoryError"}


def test_out_of_memory_recognises_allocator_errors_only() -> None:
    assert limits.out_of_memory(MemoryError())
    assert limits.out_of_memory(RuntimeError("DefaultCPUAllocator: can't allocate memory: you tried 8 GB"))
    assert not limits.out_of_memory(RuntimeError("shape mismatch"))
    assert not limits.out_of_memory(ValueError("cannot allocate memory"))


def test_allowed_cores_follows_the_cgroup_quota(tmp_path: Path) -> None:
    (tmp_path / "cpu.max").write_text("150000 100000\n")
    assert limits.allowed_cores(tmp_path) == 1
    (tmp_path / "cpu.max").write_text("max 100000\n")
    assert limits.allowed_cores(tmp_path) == limits.allowed_cores(tmp_path / "absent") >= 1
    assert limits.job_threads(0, 10**6) == 1
    assert limits.job_threads(5, 2) == 5


def test_cache_signatures_drop_tampered_and_unsigned_files(tmp_path: Path) -> None:
    key = b"worker-secret"
    (tmp_path / "decode.pkl").write_bytes(b"pickled views")
    (tmp_path / "decode.key").write_text("abc")
    assert cache_sign.sign_folder(tmp_path, key) == 2
    assert cache_sign.verify_folder(tmp_path, key) == []
    (tmp_path / "decode.pkl").write_bytes(b"cos\nsystem\n(S'echo owned'\ntR.")  # a writer of the storage
    (tmp_path / "geometry.pkl").write_bytes(b"unsigned")
    assert sorted(cache_sign.verify_folder(tmp_path, key)) == ["decode.pkl", "geometry.pkl"]
    assert not (tmp_path / "decode.pkl").exists() and not (tmp_path / "geometry.pkl").exists()
    assert (tmp_path / "decode.key").exists()
    assert cache_sign.verify_folder(tmp_path, b"another key") == ["decode.key"]


@pytest.mark.parametrize("url", ["s3:/bucket", "http://bucket/prefix", "s3://"])
def test_storage_url_must_name_a_bucket(url: str) -> None:
    from service.storage_s3 import parse_url

    with pytest.raises(ValueError, match="s3://bucket"):
        parse_url(url)
