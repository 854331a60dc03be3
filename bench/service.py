"""Benchmark: concurrent capture uploads to the service.

N clients (threads, one HTTP connection each) at once each create a job and
upload a 36-frame capture (capture.json, frames, masks) with PUT, then read
their job back. Prints the upload throughput and the request latency
percentiles per request kind, and checks that every file of every job arrived
intact: the sha256 the server answered, the sha256 it lists for the job, and
(for a local stack) the sha256 of the bytes on disk, against the client's.

By default the script starts its own stack (redis-server and uvicorn on
loopback ports, storage in a temporary folder); ``--server URL --api-key K``
measures a running deployment instead (the disk check is then skipped).

    .venv/bin/python bench/service.py                 # 20 clients x 36 frames of 1224x1024
    .venv/bin/python bench/service.py --clients 5 --width 2448 --height 2048

Writes bench/results/service.json.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from _results import table, write_results  # bench/, the script's folder

from service.testing import ServiceStack, write_noise_capture

RESULTS = Path(__file__).resolve().parent / "results" / "service.json"


def percentiles(values: list[float]) -> dict[str, float]:
    values = sorted(values)
    if not values:
        return {}

    def q(p: float) -> float:
        k = min(round(p / 100 * (len(values) - 1)), len(values) - 1)
        return values[k]

    return {
        "n": len(values),
        "p50": q(50),
        "p90": q(90),
        "p99": q(99),
        "max": values[-1],
        "mean": statistics.fmean(values),
    }


def client_run(
    url: str,
    key: str,
    capture: Path,
    files: list[str],
    digests: dict[str, str],
    out: dict,
    barrier: threading.Barrier,
) -> None:
    lat: dict[str, list[float]] = {"create": [], "put": [], "get": []}
    problems: list[str] = []
    sent = 0
    with httpx.Client(base_url=url, headers={"Authorization": f"Bearer {key}"}, timeout=120) as c:
        barrier.wait()
        t0 = time.perf_counter()
        r = c.post("/v1/jobs", json={"options": {"stop_after": "decode"}, "label": "bench"})
        lat["create"].append(time.perf_counter() - t0)
        r.raise_for_status()
        job_id = r.json()["id"]
        for rel in files:
            data = (capture / rel).read_bytes()
            t = time.perf_counter()
            r = c.put(f"/v1/jobs/{job_id}/files/{rel}", content=data)
            lat["put"].append(time.perf_counter() - t)
            sent += len(data)
            if r.status_code != 200 or r.json()["sha256"] != digests[rel]:
                problems.append(f"{rel}: HTTP {r.status_code} {r.text[:100]}")
        t = time.perf_counter()
        job = c.get(f"/v1/jobs/{job_id}").json()
        lat["get"].append(time.perf_counter() - t)
        elapsed = time.perf_counter() - t0
    listed = {f["path"]: f["sha256"] for f in job["files"]}
    if listed != digests:
        problems.append(
            f"job {job_id} lists {len(listed)} files, {sum(listed.get(k) == v for k, v in digests.items())}"
            f" of {len(digests)} with the right sha256"
        )
    out.update(job_id=job_id, latency=lat, bytes=sent, elapsed=elapsed, problems=problems, t0=t0)


def check_disk(storage: Path, job_ids: list[str], digests: dict[str, str]) -> list[str]:
    problems = []
    for job_id in job_ids:
        root = storage / "jobs" / job_id / "capture"
        for rel, digest in digests.items():
            p = root / rel
            if not p.is_file() or hashlib.sha256(p.read_bytes()).hexdigest() != digest:
                problems.append(f"{job_id}/{rel}: on disk missing or different")
    return problems


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--clients", type=int, default=20)
    ap.add_argument("--frames", type=int, default=36)
    ap.add_argument("--width", type=int, default=1224)
    ap.add_argument("--height", type=int, default=1024)
    ap.add_argument("--api-workers", type=int, default=2, help="uvicorn processes of the local stack")
    ap.add_argument("--server", help="a running service instead of a local stack")
    ap.add_argument("--api-key", help="key for --server")
    args = ap.parse_args()

    with tempfile.TemporaryDirectory(prefix="pmvir-bench-") as tmp:
        tmp = Path(tmp)
        t = time.perf_counter()
        capture = write_noise_capture(
            tmp / "capture", frames=args.frames, width=args.width, height=args.height, masks=True, seed=7
        )
        files = ["capture.json"] + sorted(p.relative_to(capture).as_posix() for p in capture.rglob("*.png"))
        digests = {rel: hashlib.sha256((capture / rel).read_bytes()).hexdigest() for rel in files}
        per_client = sum((capture / f).stat().st_size for f in files)
        print(
            f"capture: {len(files)} files, {per_client / 1e6:.1f} MB ({args.frames} frames "
            f"{args.width}x{args.height} 16-bit PNG + masks), written in {time.perf_counter() - t:.1f} s"
        )

        stack = None
        if args.server:
            url, key = args.server.rstrip("/"), args.api_key or os.environ.get("PMVIR_API_KEY", "")
        else:
            keys = tuple(f"bench-{i}" for i in range(args.clients))
            stack = ServiceStack(
                tmp / "stack",
                api_keys=keys,
                api_workers=args.api_workers,
                env={"PMVIR_MIN_FREE_BYTES": str(1 << 30)},
            )
            stack.__enter__()
            url = stack.url
        try:
            outs = [{} for _ in range(args.clients)]
            barrier = threading.Barrier(args.clients)
            threads = [
                threading.Thread(
                    target=client_run,
                    args=(
                        url,
                        key if stack is None else f"bench-{i}",
                        capture,
                        files,
                        digests,
                        outs[i],
                        barrier,
                    ),
                )
                for i in range(args.clients)
            ]
            t_start = time.perf_counter()
            for th in threads:
                th.start()
            for th in threads:
                th.join()
            wall = time.perf_counter() - t_start
            problems = [p for o in outs for p in o.get("problems", ["client crashed"])]
            if stack is not None:
                problems += check_disk(stack.storage, [o["job_id"] for o in outs if "job_id" in o], digests)
        finally:
            if stack is not None:
                stack.__exit__(None, None, None)

    total = sum(o.get("bytes", 0) for o in outs)
    lat = {
        k: percentiles([x for o in outs for x in o.get("latency", {}).get(k, [])])
        for k in ("create", "put", "get")
    }
    print(
        f"\n{args.clients} clients x {len(files)} files: {total / 1e6:.0f} MB in {wall:.2f} s "
        f"= {total / 1e6 / wall:.0f} MB/s ({total * 8 / 1e9 / wall:.2f} Gbit/s), "
        f"{sum(len(o['latency']['put']) for o in outs if 'latency' in o) / wall:.0f} uploads/s"
    )
    print("\n| request        |    n |   p50 ms |   p90 ms |   p99 ms |   max ms |")
    print("|----------------|------|----------|----------|----------|----------|")
    for kind, p in lat.items():
        if p:
            print(
                f"| {kind:<14} | {p['n']:>4} | {p['p50'] * 1e3:8.1f} | {p['p90'] * 1e3:8.1f} | "
                f"{p['p99'] * 1e3:8.1f} | {p['max'] * 1e3:8.1f} |"
            )
    intact = not problems
    checks = "the sha256 answered, the job's listing" + (
        " and the bytes on disk" if stack is not None else ""
    )
    if intact:
        print(f"\nintegrity: all {args.clients * len(files)} files intact ({checks})")
    else:
        print(f"\nintegrity: {len(problems)} PROBLEMS")
    for p in problems[:20]:
        print("  ", p)
    rows = [
        [kind, p["n"], round(p["p50"] * 1e3, 1), round(p["p90"] * 1e3, 1), round(p["p99"] * 1e3, 1),
         round(p["max"] * 1e3, 1)]
        for kind, p in lat.items()
        if p
    ]
    write_results(
        "service",
        title="Service uploads",
        path=RESULTS,
        tables=[
            table(
                f"{args.clients} clients x {len(files)} files ({args.width}x{args.height} frames): "
                f"{total / 1e6 / wall:.0f} MB/s, every file intact: {intact}",
                ["request", "n", "p50 ms", "p90 ms", "p99 ms", "max ms"],
                rows,
            )
        ],
        data={
                "clients": args.clients,
                "frames": args.frames,
                "width": args.width,
                "height": args.height,
                "files_per_client": len(files),
                "bytes_per_client": per_client,
                "bytes_total": total,
                "wall_s": wall,
                "throughput_MBps": total / 1e6 / wall,
                "latency_s": lat,
                "intact": intact,
                "problems": problems[:100],
                "api_workers": args.api_workers,
                "server": args.server or "local stack",
        },
    )
    print(f"wrote {RESULTS}")
    return 0 if intact else 1


if __name__ == "__main__":
    sys.exit(main())
