"""Benchmark: jobs per hour through the service with 1, 2 and 4 workers on this machine.

Each row starts its own stack (redis-server, the API, N Celery workers of one
job each, PMVIR_JOB_THREADS = usable cores / N), submits the same captures with
the client, and waits for every job. It prints jobs/hour, the CPU utilisation
of the workers (their CPU seconds over wall time x usable cores) and the ratio
to the ideal (the one-worker rate x min(N, cores)). The pair check runs two
jobs at once on two workers (threads split) and the same two back to back on
one worker (all threads): concurrent/back-to-back should stay within 1.1.
``--s3`` keeps the jobs in a bucket of moto's S3 server on loopback.

    .venv/bin/python bench/throughput.py                       # 8 captures, 1/2/4 workers, decode
    .venv/bin/python bench/throughput.py --captures 4 --stop-after geometry --s3

Writes bench/results/throughput.json.
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from _results import table, write_results  # bench/, the script's folder

from pmvir.client import PmvirClient
from service.testing import ServiceStack, write_noise_capture

KEY = "bench-key"


def _children_cpu() -> float:
    u = resource.getrusage(resource.RUSAGE_CHILDREN)
    return u.ru_utime + u.ru_stime


def run_batch(
    root: Path, captures: list[Path], *, workers: int, threads: int, options: dict, s3: bool
) -> tuple[float, float]:
    """Wall seconds and worker CPU seconds for all ``captures`` through a stack of ``workers`` workers."""
    env = {"PMVIR_JOB_THREADS": str(threads), "PMVIR_MIN_FREE_BYTES": "0", "PMVIR_MAX_JOBS_IN_FLIGHT": "1000"}
    st = ServiceStack(root, api_keys=(KEY,), env=env)
    cpu0 = _children_cpu()
    try:
        if s3:
            st.start_s3()
        st.start(worker=False)
        for _ in range(workers):
            st.start_worker()
        with PmvirClient(st.url, KEY, timeout=120) as client:
            ids = []
            for cap in captures:  # uploads first, then the starts: the workers begin together
                job = client.create_job(options)
                client.upload_capture(job["id"], cap)
                ids.append(job["id"])
            t0 = time.monotonic()
            for job_id in ids:
                client.start(job_id)
            for job_id in ids:
                job = client.wait(job_id, poll=0.2)
                if job["status"] != "succeeded":
                    raise RuntimeError(f"job {job_id} {job['status']}: {job.get('error')}")
            wall = time.monotonic() - t0
    finally:
        st.stop()
    return wall, _children_cpu() - cpu0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--captures", type=int, default=8, help="jobs per row (default 8)")
    p.add_argument("--frames", type=int, default=24, help="frames per capture (default 24)")
    p.add_argument("--size", type=int, default=512, help="frame width and height, px (default 512)")
    p.add_argument("--workers", default="1,2,4", help="worker counts, comma-separated (default 1,2,4)")
    p.add_argument("--stop-after", default="decode", choices=("decode", "geometry", "refine"))
    p.add_argument("--s3", action="store_true", help="jobs in moto's S3 server instead of a local folder")
    args = p.parse_args(argv)
    cores = len(os.sched_getaffinity(0))
    options = {"stop_after": args.stop_after}
    rows, record = [], []
    with tempfile.TemporaryDirectory(prefix="pmvir-throughput-") as tmp:
        caps = [
            write_noise_capture(
                Path(tmp) / f"cap{i}", frames=args.frames, width=args.size, height=args.size, seed=i
            )
            for i in range(args.captures)
        ]
        base_rate = None
        for n in (int(w) for w in args.workers.split(",")):
            threads = max(1, cores // n)
            wall, cpu = run_batch(
                Path(tmp) / f"w{n}", caps, workers=n, threads=threads, options=options, s3=args.s3
            )
            rate = 3600.0 * len(caps) / wall
            base_rate = base_rate or rate
            ideal = base_rate * min(n, cores)
            util = cpu / (wall * cores)
            rows.append([n, threads, round(wall, 1), round(rate, 1), round(util, 2), round(rate / ideal, 2)])
            record.append(
                {"workers": n, "threads": threads, "wall_s": wall, "cpu_s": cpu, "jobs_per_hour": rate}
            )
            print(
                f"{n} worker(s) x {threads} thread(s): {wall:.1f} s, {rate:.1f} jobs/h, "
                f"CPU {util:.0%}, {rate / ideal:.2f} of ideal",
                flush=True,
            )
        pair = caps[:2]
        together, _ = run_batch(
            Path(tmp) / "pair2", pair, workers=2, threads=max(1, cores // 2), options=options, s3=args.s3
        )
        serial, _ = run_batch(
            Path(tmp) / "pair1", pair, workers=1, threads=cores, options=options, s3=args.s3
        )
        ratio = together / serial
        print(
            f"two jobs at once: {together:.1f} s; back to back: {serial:.1f} s; ratio {ratio:.2f} (<= 1.1 wanted)"
        )
    storage = "S3 (moto, loopback)" if args.s3 else "local folder"
    write_results(
        "throughput",
        title=f"Service throughput ({args.captures} captures of {args.frames} frames {args.size}x{args.size}, "
        f"stop_after={args.stop_after}, {storage})",
        tables=[
            table(
                "Jobs per hour by worker count",
                ["workers", "threads/job", "wall s", "jobs/h", "CPU utilisation", "of ideal"],
                rows,
            ),
            table(
                "Two jobs at once against back to back",
                ["at once s", "back to back s", "ratio"],
                [[round(together, 1), round(serial, 1), round(ratio, 2)]],
                note="at once: two workers with half the threads each; back to back: one worker with all",
            ),
        ],
        data={"rows": record, "pair": {"together_s": together, "serial_s": serial}, "cores_usable": cores},
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
