"""A full-size capture through the service: upload, a worker capped at a memory limit, download.

The same built-in capture as ``bench/fullsize.py`` (blob, plastic, environment light, seed 7) at
2448x2048 is sent to a local stack (redis-server, the API on a loopback port and one Celery worker
whose jobs are capped at ``--memory`` through ``PMVIR_JOB_MEMORY``, the cap a deployment sets) by
``pmvir submit`` in its own process, over HTTP: the frames uploaded, the job followed, the result
zip downloaded. The job's pool process is read while it runs (``/proc``): its peak resident memory
(``VmHWM``) and its peak address space (``VmPeak``, what the cap bounds). The mesh is evaluated
against the ground truth, beside the initial surface. Prints a table and writes
bench/results/fullsize_service.json; ``--reuse`` evaluates the stored result again (the peaks and
the wall time are kept in its service_peaks.json).

    .venv/bin/python bench/fullsize_service.py [--views 12] [--size 2448x2048] [--memory 12G] [--work DIR] [--reuse]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

from _results import ROOT, capture_description, table, write_results

GIB = 2**30
API_KEY = "bench-key"


def _status_kib(pid: int) -> dict[str, int]:
    """VmHWM and VmPeak of a process in KiB (empty once it has exited)."""
    out: dict[str, int] = {}
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            key, _, value = line.partition(":")
            if key in ("VmHWM", "VmPeak"):
                out[key] = int(value.split()[0])
    except (OSError, ValueError, IndexError):
        pass
    return out


class PoolWatch(threading.Thread):
    """Polls the worker's child processes (the prefork pool that runs the job) for their peaks."""

    def __init__(self, worker_pid: int, period: float = 1.0):
        super().__init__(daemon=True)
        self.worker_pid, self.period = worker_pid, period
        self.peaks: dict[int, dict[str, int]] = {}
        self.done = threading.Event()

    def run(self) -> None:
        import psutil

        while not self.done.wait(self.period):
            try:
                children = psutil.Process(self.worker_pid).children(recursive=True)
            except psutil.Error:
                continue
            for child in children:
                seen = _status_kib(child.pid)
                if seen:
                    old = self.peaks.setdefault(child.pid, {})
                    for k, v in seen.items():
                        old[k] = max(old.get(k, 0), v)

    def peak(self, key: str) -> int:
        """The largest ``key`` (VmHWM or VmPeak) over the pool's processes, bytes."""
        return max((p.get(key, 0) for p in self.peaks.values()), default=0) * 1024


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--views", type=int, default=12, help="views (default 12)")
    p.add_argument("--size", default="2448x2048", help="frame size WxH (default 2448x2048)")
    p.add_argument("--memory", default="12G", help="the worker's PMVIR_JOB_MEMORY (default 12G)")
    p.add_argument("--work", type=Path, default=ROOT / "bench" / "results" / "fullsize")
    p.add_argument("--reuse", action="store_true", help="evaluate the stored result again without a new job")
    args = p.parse_args()

    sys.path.insert(0, str(ROOT))
    from pmvir.evaluate import evaluate_paths
    from pmvir.memory import parse_bytes
    from pmvir.synth import synthesize
    from service.testing import ServiceStack

    w, h = (int(x) for x in args.size.split("x"))
    capture = args.work / f"cap_{args.size}_{args.views}v"
    if not (capture / "capture.json").is_file():
        synthesize(capture, shape="blob", views=args.views, size=(w, h), material="plastic", lighting="envmap", seed=7)
    result = args.work / f"service_{args.size}_{args.views}v"
    limit = parse_bytes(args.memory)
    env = {"PMVIR_API_KEY": API_KEY}

    measured = result / "service_peaks.json"
    if not (args.reuse and measured.is_file()):
        with ServiceStack(args.work / "service_stack", api_keys=(API_KEY,)) as stack:
            worker = stack.start_worker(env={"PMVIR_JOB_MEMORY": str(limit)})
            watch = PoolWatch(worker.popen.pid)
            watch.start()
            t0 = time.perf_counter()
            submit = subprocess.run(
                [sys.executable, "-m", "pmvir.cli", "submit", str(capture), "--server", stack.url,
                 "--out", str(result), "--quiet"],
                env={**os.environ, **env}, capture_output=True, text=True, check=False,
            )
            wall = time.perf_counter() - t0
            watch.done.set()
            watch.join()
            if submit.returncode != 0:
                print(submit.stderr[-3000:], file=sys.stderr)
                print(stack.logs()[-3000:], file=sys.stderr)
                return 1
        peaks = {"VmHWM": watch.peak("VmHWM"), "VmPeak": watch.peak("VmPeak"), "wall_s": wall}
        measured.write_text(json.dumps(peaks))
    peaks = json.loads(measured.read_text())

    report = json.loads((result / "report.json").read_text())
    metrics = evaluate_paths(result, capture / "gt")
    initial = evaluate_paths(result / "initial.ply", capture / "gt")
    timings = report["timings_s"]
    hwm, vm_peak, wall = peaks["VmHWM"], peaks["VmPeak"], peaks["wall_s"]
    res = report.get("resolution") or {}
    record = {
        "size": args.size,
        "views": args.views,
        "memory_limit_gib": round(limit / GIB, 2),
        "working_size": res.get("refine"),
        "vertices": report.get("refine", {}).get("vertices"),
        "job_peak_rss_gib": round(hwm / GIB, 2),
        "job_peak_address_space_gib": round(vm_peak / GIB, 2),
        "stage_s": {k: round(float(timings[k]), 1) for k in ("decode", "geometry", "refine") if k in timings},
        "submit_wall_s": round(wall, 1),
        "initial_accuracy": initial.accuracy,
        "accuracy": metrics.accuracy,
        "completeness": metrics.completeness,
        "normal_error_median": getattr(metrics, "normal_error_median", None),
    }
    columns = [
        "frames", "views", "PMVIR_JOB_MEMORY GiB", "working size", "vertices", "job peak RSS GiB",
        "job peak address space GiB", "decode s", "geometry s", "refine s", "upload to download s",
        "initial accuracy x1e-2", "accuracy x1e-2", "completeness x1e-2", "normal error median deg",
    ]
    row = [
        args.size, args.views, record["memory_limit_gib"], record["working_size"], record["vertices"],
        record["job_peak_rss_gib"], record["job_peak_address_space_gib"], record["stage_s"].get("decode"),
        record["stage_s"].get("geometry"), record["stage_s"].get("refine"), record["submit_wall_s"],
        round(initial.accuracy * 100, 4), round(metrics.accuracy * 100, 4), round(metrics.completeness * 100, 4),
        None if record["normal_error_median"] is None else round(record["normal_error_median"], 2),
    ]
    note = (
        f"Capture: {capture_description(capture)}. Sent by `pmvir submit` over HTTP to a local stack (redis-server, "
        "the API, one Celery worker with PMVIR_JOB_MEMORY set); the job's pool process read from /proc every second. "
        "The cap bounds the address space (RLIMIT_AS), which runs above the resident memory by the libraries' "
        "mappings and allocator arenas. The initial accuracy is the geometric stage's surface: the refinement's "
        "gain is the step to the next column."
    )
    t = table("A full-size capture through the service", columns, [row], note=note)
    print(" | ".join(columns))
    print(" | ".join(str(c) for c in row))
    write_results("fullsize_service", title="A full-size capture through the service", tables=[t], data=record)
    return 0


if __name__ == "__main__":
    sys.exit(main())
