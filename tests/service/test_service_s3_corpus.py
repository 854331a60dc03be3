"""The hostile-input, security and fault corpora again, with the jobs in an S3 bucket.

The tests are those of ``test_service_hostile``, ``test_service_security`` and
``test_service_faults`` that send bytes through the storage (uploads, zipped
captures, frame headers, validation, results; a Redis restart between jobs; a
worker killed mid-job is ``test_service_multihost``'s), run here against a stack whose
``PMVIR_STORAGE_URL`` is a bucket of moto's S3 server on loopback: no 5xx, nothing
lost, no other tenant's job readable. The module's own last tests check the
bucket: it holds no object of a job the store does not know, and no upload left
half-way.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
import test_service_faults as faults
from test_service_hostile import (  # noqa: F401 - collected here, against the bucket
    test_capture_json_with_a_huge_number_or_deep_nesting_is_422,
    test_chunked_body_with_an_invalid_chunk_size_logs_no_traceback,
    test_generated_bodies_never_get_a_5xx,
    test_png_declaring_a_huge_image_is_refused_from_its_header_with_the_other_errors,
    test_zip_member_name_flagged_utf8_with_invalid_bytes_is_422,
    test_zip_member_with_an_unsupported_compression_is_refused_by_name,
    test_zip_of_many_small_compressible_members_is_refused_as_a_whole,
    test_zip_options_field_with_a_5000_digit_integer_is_422,
)
from test_service_security import (  # noqa: F401 - collected here (with their fixtures), against the bucket
    c,
    test_another_keys_job_is_404_everywhere,
    test_bad_upload_paths_are_rejected,
    test_frame_count_limit_is_413,
    test_job_byte_limit_is_413,
    test_oversize_streamed_frame_without_length_is_413,
    test_zip_bomb_is_rejected_before_extraction,
    test_zip_member_outside_the_layout_is_422,
    test_zip_whose_member_lies_about_its_size_is_422,
    test_zip_without_manifest_is_422_when_its_frames_are_not_frames,
    zc,
)

from service.store import JobStore
from service.testing import ServiceStack

from svc_helpers import FLIGHT_KEY, FUZZ_KEY, KEY, OTHER_KEY, client_for, new_job, running_stack

pytest.importorskip("boto3")
pytest.importorskip("moto")

BUCKET = "pmvir-corpus"


@pytest.fixture(scope="module")
def stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceStack]:
    """moto's S3 server, Redis, the API and one worker, the jobs in a bucket (the module's stack)."""
    keys = (KEY, OTHER_KEY, FLIGHT_KEY, FUZZ_KEY)
    with running_stack(tmp_path_factory.mktemp("s3stack"), keys=keys, bucket=BUCKET) as st:
        yield st


@pytest.fixture()
def fresh_stack(tmp_path: Path) -> Iterator[ServiceStack]:
    """A bucket-backed stack of its own for a fault test (Redis with an append-only file)."""
    with running_stack(tmp_path / "stack", keys=(KEY,), bucket=BUCKET, worker=False, appendonly=True) as st:
        yield st


@pytest.mark.slow
def test_redis_restarted_between_jobs_the_next_job_runs(fresh_stack: ServiceStack, small_capture: Path) -> None:
    faults.test_redis_restarted_between_jobs_the_next_job_runs(fresh_stack, small_capture)


def _bucket_jobs(stack: ServiceStack) -> dict[str, list[str]]:
    """The bucket's objects by job id."""
    out: dict[str, list[str]] = {}
    pages = stack.s3_client().get_paginator("list_objects_v2").paginate(Bucket=BUCKET, Prefix="jobs-root/jobs/")
    for page in pages:
        for obj in page.get("Contents", []):
            job_id, rest = obj["Key"][len("jobs-root/jobs/") :].split("/", 1)
            out.setdefault(job_id, []).append(rest)
    return out


def test_the_bucket_holds_only_jobs_the_store_knows(stack: ServiceStack, small_capture: Path) -> None:
    with client_for(stack) as api:
        kept = new_job(api, small_capture)  # a job of this test, to see that the bucket is the storage
    store = JobStore.from_url(stack.redis_url)
    objects = _bucket_jobs(stack)
    uploaded = [f"capture/{p.relative_to(small_capture).as_posix()}" for p in small_capture.rglob("*") if p.is_file()]
    assert sorted(objects[kept]) == sorted(uploaded)
    assert not (stack.storage / "jobs" / kept).exists()
    assert [j for j in objects if store.get(j) is None] == []
    assert [(j, k) for j, keys in objects.items() for k in keys if not k.startswith(("capture/", "result/"))] == []


def test_the_api_logged_no_traceback(stack: ServiceStack) -> None:
    assert stack.api is not None
    assert "Traceback" not in stack.api.log.read_text(errors="replace")
