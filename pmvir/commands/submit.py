"""``pmvir submit CAPTURE --server URL``: run a capture on the service and fetch the result.

Checks the capture locally (manifest, file headers), creates a job with the
options (``--config`` JSON, ``--set key=value``, ``--stop-after``: the same
PipelineConfig tree as ``pmvir reconstruct``), uploads the capture with
retries (large files resumable) and a progress bar, starts the job, polls it
with a progress bar, and downloads ``result.zip`` into ``--out`` (extracted).
A small ``.zip`` capture goes up in one request. Ctrl-C while waiting cancels
the job. With only the ``client`` extra installed (no numpy/OpenCV), the local
check of the frame headers is skipped and the service does it. Exit status: 0 succeeded, 1 the job failed or was canceled, 2 a
problem with the capture, the options or the service.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
import uuid
import zipfile
from pathlib import Path, PurePosixPath
from typing import Any

from pmvir.commands.options import add_option_arguments, build_config
from pmvir.errors import CaptureError, ConfigError


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "submit",
        help="upload a capture to the service, wait for the job and download the result",
        description="Upload CAPTURE (folder or .zip) to a pmvir service, start the job, show its progress, "
        "and download the result into --out. The API key comes from --api-key or PMVIR_API_KEY.",
    )
    p.add_argument("capture", type=Path, help="capture folder, or a zipped capture")
    p.add_argument("--server", required=True, help="service base URL, e.g. http://localhost:8000")
    p.add_argument(
        "--api-key", default=None, help="API key (default: the PMVIR_API_KEY environment variable)"
    )
    p.add_argument("--out", type=Path, default=None, help="result folder (default: <capture>-result)")
    add_option_arguments(p)
    p.add_argument("--label", default=None, help="a label for the job")
    p.add_argument("--no-wait", action="store_true", help="start the job, print its id and exit")
    p.add_argument("--poll", type=float, default=1.0, help="seconds between status polls (default 1)")
    p.add_argument("--timeout", type=float, default=None, help="give up waiting after this many seconds")
    p.add_argument("--retries", type=int, default=5, help="retries per request (default 5)")
    p.add_argument(
        "--zip-limit",
        type=int,
        default=64 << 20,
        help="a .zip capture up to this many bytes is sent in one request (default 64 MiB)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.add_argument(
        "--resume",
        action="store_true",
        help="continue this capture's last interrupted submission to this server: the same job, files "
        "already there (same sha256) skipped, a partial upload continued",
    )
    p.add_argument("--parallel", type=int, default=4, help="files uploaded at once (default 4)")
    p.set_defaults(func=run)


def _state_path(server: str, capture: Path) -> Path:
    """Where a submission's state is kept: one JSON file per (server, capture folder or zip)."""
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "pmvir" / "submit"
    digest = hashlib.sha256(f"{server.rstrip('/')}\0{capture.resolve()}".encode()).hexdigest()[:32]
    return base / f"{digest}.json"


def _load_state(path: Path, resume: bool) -> dict[str, Any]:
    """The state to resume from (its idempotency key and job id), or a fresh one."""
    if resume:
        try:
            state = json.loads(path.read_text())
            if isinstance(state, dict) and isinstance(state.get("idempotency_key"), str):
                return state
        except (OSError, ValueError):
            pass
    return {"idempotency_key": uuid.uuid4().hex}


def _save_state(path: Path, state: dict[str, Any]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(state))
    tmp.replace(path)


def _bar(total: float | None, desc: str, unit: str, quiet: bool, **kw: Any):
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit=unit, disable=quiet, file=sys.stderr, dynamic_ncols=True, **kw)


def _upload(client: Any, job_id: str, files: dict[str, Path], quiet: bool, parallel: int) -> list[str]:
    """Upload what the job lacks (files it holds with the same sha256 are skipped)."""
    total = sum(local.stat().st_size for local in files.values())
    with _bar(total, "upload", "B", quiet, unit_scale=True, unit_divisor=1024) as bar:
        return list(client.upload_missing(job_id, files, parallel=parallel, on_bytes=bar.update))


def _files_of(capture: Path) -> dict[str, Path]:
    """The files to upload, by their path in the capture layout: those capture.json names (all
    of the layout when the library's capture reader is not installed). A folder of frames without
    capture.json sends its frames alone (as ``frames/<name>``): the service infers the manifest."""
    try:
        from pmvir.capture import open_capture
    except ModuleNotFoundError:
        from pmvir.client import capture_files

        root = capture if capture.is_dir() else capture.parent
        return {rel: root / rel for rel in capture_files(root)}
    with open_capture(capture) as cap:
        files = [] if cap.inferred else ["capture.json"]
        for f in cap.frames:
            files.append(f.file)
            if f.mask:
                files.append(f.mask)
        files += [g for g in ("gt/mesh.ply", "gt/illumination.json") if (cap.root / g).is_file()]
        return {rel: cap.root / cap.on_disk(rel) for rel in files}


def _check_locally(capture: Path) -> None:
    """The manifest and frame headers, when the library's capture reader is installed."""
    try:
        from pmvir.capture import validate_capture
    except ModuleNotFoundError:
        return
    problems = validate_capture(capture, decode_frames=False)
    if problems:
        raise CaptureError(capture.name, "; ".join(str(p) for p in problems))


def _wait(client: Any, job_id: str, args: argparse.Namespace) -> dict[str, Any]:
    with _bar(
        100.0, "queued", "%", args.quiet, bar_format="{desc}: {percentage:3.0f}%|{bar}| {elapsed}"
    ) as bar:

        def update(job: dict[str, Any]) -> None:
            bar.set_description_str(job["stage"] or job["status"])
            bar.update(round(job["progress"] * 100.0, 1) - bar.n)

        try:
            return client.wait(job_id, poll=args.poll, timeout=args.timeout, on_update=update)
        except KeyboardInterrupt:
            client.cancel(job_id)
            print(f"pmvir submit: job {job_id} canceled", file=sys.stderr)
            raise


def _extract(zip_path: Path, out: Path) -> None:
    with zipfile.ZipFile(zip_path) as zf:
        for info in zf.infolist():
            parts = PurePosixPath(info.filename).parts
            if info.filename.startswith("/") or ".." in parts or "\\" in info.filename:
                raise CaptureError(zip_path.name, f"result member {info.filename!r} is not a relative path")
        zf.extractall(out)


def run(args: argparse.Namespace) -> int:
    from pmvir.client import PmvirClient

    key = args.api_key or os.environ.get("PMVIR_API_KEY")
    if not key:
        raise ConfigError("no API key: pass --api-key or set PMVIR_API_KEY")
    options = build_config(args).model_dump(mode="json")
    _check_locally(args.capture)
    out = args.out or args.capture.with_name(args.capture.stem + "-result")
    label = args.label or args.capture.stem
    one_request = args.capture.suffix.lower() == ".zip" and args.capture.stat().st_size <= args.zip_limit
    state_path = _state_path(args.server, args.capture)
    state = _load_state(state_path, args.resume)
    with PmvirClient(args.server, key, retries=args.retries) as client:
        if one_request:
            job = client.create_job_from_zip(
                args.capture, options, label=label, idempotency_key=state["idempotency_key"]
            )
        else:
            job = client.create_job(options, label=label, idempotency_key=state["idempotency_key"])
        job_id = job["id"]
        _save_state(state_path, {**state, "job_id": job_id, "server": args.server})
        if job["status"] == "created" and not one_request:
            if job.get("files"):
                print(f"pmvir submit: resuming job {job_id}", file=sys.stderr)
            _upload(client, job_id, _files_of(args.capture), args.quiet, args.parallel)
        print(f"pmvir submit: job {job_id}", file=sys.stderr)
        if job["status"] == "created":
            client.start(job_id)
        if args.no_wait:
            print(job_id)
            return 0
        job = _wait(client, job_id, args)
        state_path.unlink(missing_ok=True)  # the job ended: nothing to resume
        if job["status"] != "succeeded":
            print(
                f"pmvir submit: job {job_id} {job['status']}: {job.get('error') or ''}".rstrip(": "),
                file=sys.stderr,
            )
            return 1
        out.mkdir(parents=True, exist_ok=True)
        with _bar(None, "download", "B", args.quiet, unit_scale=True, unit_divisor=1024) as bar:
            zip_path = client.download(job_id, "result.zip", out / "result.zip", on_bytes=bar.update)
        _extract(zip_path, out)
    print(out)
    return 0
