"""Running the real service locally: redis-server, ``pmvir serve`` and ``pmvir worker`` as processes.

Used by the service's tests and by ``bench/service.py``; handy for trying the
service by hand too::

    with ServiceStack(tmp_dir, api_keys=("k1",)) as stack:
        stack.start_worker()
        httpx.get(stack.url + "/readyz")

Every process runs in its own session (process group), so :meth:`Proc.kill`
can SIGKILL it with its children, as ``docker kill`` would; everything is
stopped on exit, also when the body raised. Output goes to log files under the
stack's folder (:meth:`ServiceStack.logs` for a failing test's report).

:func:`write_noise_capture` writes a valid capture of random 12-bit mosaics:
content for transport and load tests, not for reconstruction.
"""

from __future__ import annotations

import json
import os
import random
import shutil
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from pmvir.io.frames import write_frame


def _ephemeral_range() -> tuple[int, int]:
    """The kernel's range for outgoing connections' local ports (Linux; the IANA range elsewhere)."""
    try:
        lo, hi = Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()
        return int(lo), int(hi)
    except (OSError, ValueError):
        return 49152, 65535


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on right now, outside the ephemeral range.

    A port the kernel hands out for ``bind(0)`` lies in the ephemeral range, where
    any outgoing connection (a Redis client, an HTTP poll) may be given it again
    between this check and the server's own bind ("address already in use"; seen
    in CI). Ports below that range are only ever taken by an explicit bind.
    """
    lo, _ = _ephemeral_range()
    rng = random.Random(os.getpid() ^ time.monotonic_ns())
    for _ in range(200):
        port = rng.randrange(max(1024, lo - 12000), lo)
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
            return port
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _lost_bind(proc: Proc) -> bool:
    """Whether ``proc`` exited because its port was taken after :func:`free_port` chose it."""
    return proc.popen.poll() is not None and "already in use" in proc.tail().lower()


def _wait(pred, timeout: float, what: str, proc: Proc | None = None) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc is not None and proc.popen.poll() is not None:
            raise RuntimeError(f"{what}: process exited with {proc.popen.returncode}\n{proc.tail()}")
        try:
            if pred():
                return
        except Exception:  # noqa: BLE001 - not up yet: poll again
            pass
        time.sleep(0.05)
    raise TimeoutError(f"{what}: not ready after {timeout} s" + (f"\n{proc.tail()}" if proc else ""))


class Proc:
    """A child process in its own session, logging to a file."""

    def __init__(
        self,
        name: str,
        argv: list[str],
        *,
        log: Path,
        env: Mapping[str, str] | None = None,
        cwd: Path | None = None,
    ):
        self.name = name
        self.log = log
        self._fh = open(log, "ab")  # noqa: SIM115 - held for the life of the process, closed by kill()
        self.popen = subprocess.Popen(
            argv,
            stdout=self._fh,
            stderr=subprocess.STDOUT,
            env=dict(env or os.environ),
            cwd=cwd,
            start_new_session=True,
        )

    @property
    def pid(self) -> int:
        return self.popen.pid

    def alive(self) -> bool:
        return self.popen.poll() is None

    def tail(self, n: int = 4000) -> str:
        try:
            return self.log.read_text(errors="replace")[-n:]
        except OSError:
            return ""

    def _signal_group(self, sig: int) -> None:
        try:
            os.killpg(self.popen.pid, sig)
        except ProcessLookupError:
            pass

    def kill(self) -> None:
        """SIGKILL the process and everything in its group, at once."""
        self._signal_group(signal.SIGKILL)
        self.popen.wait(timeout=10)
        self._fh.close()

    def stop(self, timeout: float = 10.0) -> None:
        """SIGTERM the group, then SIGKILL what is left after ``timeout`` seconds."""
        if self.popen.poll() is None:
            self._signal_group(signal.SIGTERM)
            try:
                self.popen.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                pass
        self._signal_group(signal.SIGKILL)  # stray children of the group
        if self.popen.poll() is None:
            self.popen.wait(timeout=10)
        self._fh.close()


class ServiceStack:
    """redis-server, uvicorn (the API) and Celery workers on loopback ports, sharing one storage root.

    Args:
        root: a folder for storage, Redis data and logs.
        api_keys: the keys the API accepts.
        env: more PMVIR_* settings for the API and the workers (strings).
        appendonly: Redis persists to an append-only file (state survives a Redis restart).
        api_workers: uvicorn worker processes.
    """

    def __init__(
        self,
        root: str | Path,
        *,
        api_keys: tuple[str, ...] = ("test-key",),
        env: Mapping[str, str] | None = None,
        appendonly: bool = False,
        api_workers: int = 1,
    ):
        if shutil.which("redis-server") is None:
            raise RuntimeError("redis-server is not installed")
        self.root = Path(root)
        self.storage = self.root / "storage"
        self.redis_dir = self.root / "redis"
        self.log_dir = self.root / "logs"
        for d in (self.storage, self.redis_dir, self.log_dir):
            d.mkdir(parents=True, exist_ok=True)
        self.redis_port = free_port()
        self.api_port = free_port()
        self.url = f"http://127.0.0.1:{self.api_port}"
        self.redis_url = f"redis://127.0.0.1:{self.redis_port}/0"
        self.appendonly = appendonly
        self.api_workers = api_workers
        self.api_keys = api_keys
        self.env = {
            **os.environ,
            "PMVIR_REDIS_URL": self.redis_url,
            "PMVIR_STORAGE": str(self.storage),
            "PMVIR_API_KEYS": ",".join(api_keys),
            **(env or {}),
        }
        self.redis: Proc | None = None
        self.s3: Proc | None = None
        self.s3_url = ""
        self.api: Proc | None = None
        self.workers: list[Proc] = []
        self._n = 0
        self._redis_started = self._api_started = False

    # -- parts

    def _first_start(
        self, start: Callable[[], Proc], part: str, started: bool, move: Callable[[], None]
    ) -> Proc:
        """Run ``start``; a first start whose port was taken meanwhile moves (``move``) and tries again.

        A restart keeps its port (clients hold the URL), so it is never moved.
        """
        for attempt in range(3):
            try:
                return start()
            except (RuntimeError, TimeoutError):
                proc = getattr(self, part)
                if started or proc is None or not _lost_bind(proc) or attempt == 2:
                    raise
                proc.stop()
                move()
        raise AssertionError("unreachable")

    def start_redis(self) -> Proc:
        def move() -> None:
            self.redis_port = free_port()
            self.redis_url = f"redis://127.0.0.1:{self.redis_port}/0"
            self.env["PMVIR_REDIS_URL"] = self.redis_url

        return self._first_start(self._start_redis, "redis", self._redis_started, move)

    def _start_redis(self) -> Proc:
        argv = [
            "redis-server",
            "--port",
            str(self.redis_port),
            "--bind",
            "127.0.0.1",
            "--save",
            "",
            "--dir",
            str(self.redis_dir),
            "--daemonize",
            "no",
            "--protected-mode",
            "yes",
            "--appendonly",
            "yes" if self.appendonly else "no",
        ]
        if self.appendonly:
            argv += ["--appendfsync", "always"]
        self.redis = Proc("redis", argv, log=self.log_dir / "redis.log", cwd=self.redis_dir)
        import redis as redis_py

        client = redis_py.Redis(host="127.0.0.1", port=self.redis_port, socket_connect_timeout=0.5)
        _wait(client.ping, 15, "redis-server", self.redis)
        client.close()
        self._redis_started = True
        return self.redis

    def start_s3(self, bucket: str = "pmvir-test") -> Proc:
        """moto's standalone S3 server on a loopback port, with ``bucket``; the API and the workers
        started afterwards keep their jobs in ``s3://<bucket>/jobs-root`` (call before :meth:`start`)."""
        port = free_port()
        self.s3_url = f"http://127.0.0.1:{port}"
        creds = {"AWS_ACCESS_KEY_ID": "testing", "AWS_SECRET_ACCESS_KEY": "testing", "AWS_DEFAULT_REGION": "us-east-1"}
        argv = [sys.executable, "-m", "moto.server", "-H", "127.0.0.1", "-p", str(port)]
        self.s3 = Proc("s3", argv, log=self.log_dir / "s3.log", env={**os.environ, **creds})
        client = self.s3_client()
        _wait(lambda: client.list_buckets() is not None, 30, "moto_server", self.s3)
        client.create_bucket(Bucket=bucket)
        self.env.update(
            creds,
            PMVIR_STORAGE_URL=f"s3://{bucket}/jobs-root",
            PMVIR_S3_ENDPOINT_URL=self.s3_url,
            PMVIR_SCRATCH=str(self.storage / "scratch"),
        )
        return self.s3

    def s3_client(self) -> Any:
        """A boto3 S3 client of the stack's S3 server."""
        import boto3

        return boto3.client(
            "s3",
            endpoint_url=self.s3_url,
            aws_access_key_id="testing",
            aws_secret_access_key="testing",
            region_name="us-east-1",
        )

    def start_api(self) -> Proc:
        def move() -> None:
            self.api_port = free_port()
            self.url = f"http://127.0.0.1:{self.api_port}"

        return self._first_start(self._start_api, "api", self._api_started, move)

    def _start_api(self) -> Proc:
        argv = [
            sys.executable,
            "-m",
            "pmvir.cli",
            "serve",
            "--host",
            "127.0.0.1",
            "--port",
            str(self.api_port),
            "--log-level",
            "warning",
            "--workers",
            str(self.api_workers),
        ]
        self.api = Proc("api", argv, log=self.log_dir / "api.log", env=self.env)
        import httpx

        _wait(lambda: httpx.get(self.url + "/healthz", timeout=1).status_code == 200, 30, "uvicorn", self.api)
        self._api_started = True
        return self.api

    def start_worker(
        self, *, pool: str = "prefork", wait: bool = True, env: Mapping[str, str] | None = None
    ) -> Proc:
        """A Celery worker (one job at a time); waits until it consumes from the queue.

        ``env`` overrides settings of this worker alone (a host of its own: PMVIR_STORAGE, PMVIR_SCRATCH).
        """
        self._n += 1
        log = self.log_dir / f"worker{self._n}.log"
        argv = [
            sys.executable,
            "-m",
            "pmvir.cli",
            "worker",
            f"--pool={pool}",
            "--concurrency=1",
            "--hostname",
            f"w{self._n}@%h",
            "--loglevel=INFO",
        ]
        w = Proc(f"worker{self._n}", argv, log=log, env={**self.env, **(env or {})})
        self.workers.append(w)
        if wait:
            self.wait_worker(w)
        return w

    @staticmethod
    def wait_worker(worker: Proc, timeout: float = 60) -> None:
        """Wait until a worker started with ``wait=False`` consumes from the queue."""
        _wait(lambda: " ready." in worker.tail(20000), timeout, "celery worker", worker)

    def start(self, *, worker: bool = True) -> ServiceStack:
        """Start whatever is not running yet (Redis, the API, and one worker when ``worker``); the worker
        starts before the API and both load at once."""
        if self.redis is None:
            self.start_redis()
        booting = self.start_worker(wait=False) if worker and not self.workers else None
        if self.api is None:
            self.start_api()
        if booting is not None:
            self.wait_worker(booting)
        return self

    def restart_api(self) -> Proc:
        if self.api is not None:
            self.api.stop()
        return self.start_api()

    def restart_redis(self) -> Proc:
        if self.redis is not None:
            self.redis.stop()
        return self.start_redis()

    def stop(self) -> None:
        for w in self.workers:
            w.stop()
        self.workers = []
        for p in (self.api, self.redis, self.s3):
            if p is not None:
                p.stop()
        self.api = self.redis = self.s3 = None

    def logs(self) -> str:
        parts = []
        for p in [*self.workers, self.api, self.redis, self.s3]:
            if p is not None:
                parts.append(f"--- {p.name} ({p.log.name}) ---\n{p.tail()}")
        return "\n".join(parts)

    def __enter__(self) -> ServiceStack:
        try:
            return self.start(worker=False)
        except BaseException:
            self.stop()
            raise

    def __exit__(self, *exc: object) -> None:
        self.stop()


def write_noise_capture(
    root: str | Path,
    *,
    frames: int,
    width: int = 64,
    height: int = 48,
    seed: int = 0,
    masks: bool = False,
    dop: float = 0.0,
) -> Path:
    """A valid IMX250MYR capture of random 12-bit mosaics as 16-bit PNGs (for transport and load tests).

    Args:
        root: the capture folder (created).
        frames: number of frames.
        width, height: frame size in pixels (multiples of 4).
        seed: random seed; the content is a smooth random field plus noise, so PNG
            compression stays realistic (neither all noise nor constant).
        masks: also write masks/<name>.png (8-bit, all foreground).
        dop: degree of linear polarization of every pixel (angle 30 degrees): the field is
            split over the four polarizer angles of the IMX250MYR mosaic (0: unpolarized).

    Returns:
        The capture folder.
    """
    if width % 4 or height % 4:
        raise ValueError(f"width and height must be multiples of 4, got {width}x{height}")
    root = Path(root)
    (root / "frames").mkdir(parents=True, exist_ok=True)
    if masks:
        (root / "masks").mkdir(exist_ok=True)
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float32)
    entries = []
    for i in range(frames):
        fx, fy, ph = rng.uniform(0.005, 0.05), rng.uniform(0.005, 0.05), rng.uniform(0, 6.28)
        base = 1500 + 1000 * np.sin(fx * xx + ph) * np.cos(fy * yy)
        if dop > 0.0:
            base = base * _polarizer_gain(height, width, dop)
        samples = np.clip(base + rng.normal(0, 60, size=base.shape), 0, 4095).astype(np.uint16)
        name = f"{i:03d}"
        write_frame(root / "frames" / f"{name}.png", samples, bit_depth=12)
        entry: dict = {"file": f"frames/{name}.png"}
        if masks:
            write_frame(root / "masks" / f"{name}.png", np.full((height, width), 255, np.uint8), bit_depth=8)
            entry["mask"] = f"masks/{name}.png"
        entries.append(entry)
    manifest = {
        "format": "pmvir-capture/1",
        "sensor": {"layout": "IMX250MYR", "bit_depth": 12, "black_level": 0, "white_level": 4095},
        "frames": entries,
    }
    (root / "capture.json").write_text(json.dumps(manifest, indent=1))
    return root


def _polarizer_gain(height: int, width: int, dop: float) -> np.ndarray:
    """Per mosaic pixel ``1 + dop cos(2 (theta - 30 deg))`` for its polarizer angle theta (IMX250MYR)."""
    from pmvir.polarization.layout import ANGLES_DEG, IMX250MYR, mosaic

    theta = np.deg2rad(np.asarray(ANGLES_DEG, dtype=np.float64))
    gain = 1.0 + dop * np.cos(2.0 * (theta - np.deg2rad(30.0)))
    per_pixel = np.broadcast_to(gain[:, None], (height, width, 4, 3))
    out: np.ndarray = mosaic(np.ascontiguousarray(per_pixel), IMX250MYR)
    return out
