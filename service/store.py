"""Job state in Redis, under the service's own keys (not Celery's result backend).

Keys (``P`` is ``Settings.key_prefix``)::

    P:job:<id>             hash: status, stage, progress, options, owner, times, error, run_id, ...
    P:job:<id>:files       hash: capture path -> {"size", "sha256"} of every complete upload
    P:job:<id>:partial     hash: capture path -> total size declared by Content-Range
    P:job:<id>:uploads     zset: upload tokens in progress, scored by their expiry time
    P:job:<id>:offers      hash: presigned upload id -> {"path", "size", "sha256", "expires_at"}
    P:job:<id>:starting    string with a TTL: held while POST /start validates the capture
    P:job:<id>:lease       string with a TTL: the run id of the worker running the job (heartbeat)
    P:job:<id>:log         list of JSON lines {"t", "msg"}
    P:owner:<owner>:jobs   zset: the owner's job ids by creation time
    P:owner:<owner>:open   set: the owner's unfinished jobs (created, validating, queued, running)
    P:running              set: jobs in status running (scanned for lapsed leases)
    P:idem:<owner>:<hash>  string with a TTL: Idempotency-Key -> job id
    P:job:<id>:webhook     list of JSON delivery attempts of the job's webhook
    P:expiry               zset: finished jobs with a ttl, scored by when they are to be deleted
    P:webhooks             zset: jobs whose webhook event is due, scored by the next attempt's time
    P:worker:<name>        string with a TTL: a live worker's JSON self-description (heartbeat)
    P:validating           zset: jobs whose capture is being validated, scored by when it began
    P:ready:<owner>        list: the owner's queued jobs in dispatch order (fair dispatch)
    P:ready                zset: owners with ready jobs, scored by when each was last served
    P:served               hash: owner -> the dispatch counter's value when it was last served
    P:dispatch             counter: one tick per job dispatched

Fair dispatch: the Celery message of a job only wakes a worker. Whatever job it
names, the worker takes the next job of the tenant served least recently
(:meth:`JobStore.claim_next`, one Lua script), so a tenant with many queued jobs
does not hold back another's: with several workers on several hosts alike, as
every claim is one atomic step in Redis. There is a message per queued job, so
no ready job waits for a wake-up; a message that finds nothing ready falls back
to its own job (a running job whose lease lapsed, claimed again at once).

Every state change that depends on the current state is one Lua script
(:mod:`service.store_scripts`), so
concurrent API processes and workers never interleave a check and a write.
Progress only grows; a worker's writes count only while its run id is the
job's current one (a stale, superseded run changes nothing).
"""

from __future__ import annotations

import hashlib
import json
import time
from typing import Any

import redis
import redis.lock

from service import store_scripts as scripts
from service.store_types import TERMINAL, Claim, FileInfo, Gate, IdempotentJob, Job, JobStatus
from service.store_types import gate as _gate

__all__ = ["TERMINAL", "Claim", "FileInfo", "Gate", "IdempotentJob", "Job", "JobStatus", "JobStore"]


class JobStore:
    """The service's job records in Redis (see the module docstring for the keys).

    Args:
        client: a ``redis.Redis`` with ``decode_responses=True``.
        prefix: key prefix.
    """

    def __init__(self, client: redis.Redis, *, prefix: str = "pmvir"):
        # decode_responses=True: every reply is str, which redis-py's `bytes | str` types cannot say.
        self.r: Any = client
        self.p = prefix
        self._create = client.register_script(scripts.CREATE)
        self._transition = client.register_script(scripts.TRANSITION)
        self._claim = client.register_script(scripts.CLAIM)
        self._claim_next = client.register_script(scripts.CLAIM_NEXT)
        self._heartbeat = client.register_script(scripts.HEARTBEAT)
        self._progress = client.register_script(scripts.PROGRESS)
        self._requeue = client.register_script(scripts.REQUEUE)
        self._upload_begin = client.register_script(scripts.UPLOAD_BEGIN)
        self._upload_commit = client.register_script(scripts.UPLOAD_COMMIT)
        self._start_lock = client.register_script(scripts.START_LOCK)
        self._cancel = client.register_script(scripts.CANCEL)
        self._delete_if_equal = client.register_script(scripts.DELETE_IF_EQUAL)

    @classmethod
    def from_url(cls, url: str, *, prefix: str = "pmvir") -> JobStore:
        client = redis.Redis.from_url(
            url, decode_responses=True, socket_timeout=10, socket_connect_timeout=5, health_check_interval=15
        )
        return cls(client, prefix=prefix)

    # -- keys

    def key(self, job_id: str, part: str | None = None) -> str:
        return f"{self.p}:job:{job_id}" + (f":{part}" if part else "")

    def _owner_jobs(self, owner: str) -> str:
        return f"{self.p}:owner:{owner}:jobs"

    def _owner_open(self, owner: str) -> str:
        return f"{self.p}:owner:{owner}:open"

    @property
    def _running(self) -> str:
        return f"{self.p}:running"

    @property
    def _expiry(self) -> str:
        return f"{self.p}:expiry"

    @property
    def _webhooks(self) -> str:
        return f"{self.p}:webhooks"

    def _ready_keys(self, owner: str) -> list[str]:
        """KEYS of the scripts that make a job ready: the owner's ready list, ready owners, served."""
        return [f"{self.p}:ready:{owner}", f"{self.p}:ready", f"{self.p}:served"]

    def _ending_keys(self, job_id: str, owner: str) -> list[str]:
        """KEYS of the scripts that may end or queue a job: job, owner open, running, lease, expiry,
        webhooks, and the :meth:`_ready_keys`."""
        return [
            self.key(job_id),
            self._owner_open(owner),
            self._running,
            self.key(job_id, "lease"),
            self._expiry,
            self._webhooks,
            *self._ready_keys(owner),
        ]

    def ping(self) -> bool:
        return bool(self.r.ping())

    # -- jobs

    def create(
        self,
        job_id: str,
        owner: str,
        *,
        options: dict[str, Any],
        label: str | None,
        max_open: int,
        extra: dict[str, str] | None = None,
    ) -> int | None:
        """Create a job in status ``created``.

        Returns:
            None when created, else the owner's number of unfinished jobs (the limit was reached).
        """
        now = time.time()
        fields = {
            "id": job_id,
            "owner": owner,
            "status": JobStatus.CREATED,
            "options": json.dumps(options),
            "label": label or "",
            "progress": "0",
            "created_at": repr(now),
            "updated_at": repr(now),
            "deliveries": "0",
            "cancel": "0",
            "stage_timings": "{}",
            **(extra or {}),
        }
        flat = [x for kv in fields.items() for x in kv]
        res = self._create(
            keys=[self.key(job_id), self._owner_jobs(owner), self._owner_open(owner)],
            args=[job_id, max_open, repr(now), *flat],
        )
        if res == -1:
            raise RuntimeError(f"job id {job_id} already exists")
        return None if res == -2 else int(res)

    def get(self, job_id: str) -> Job | None:
        h = self.r.hgetall(self.key(job_id))
        return Job.from_hash(h) if h else None

    def list_for(self, owner: str, *, offset: int, limit: int) -> tuple[list[Job], int]:
        """The owner's jobs, newest first, and how many there are in all."""
        key = self._owner_jobs(owner)
        ids = self.r.zrevrange(key, offset, offset + limit - 1)
        total = self.r.zcard(key)
        pipe = self.r.pipeline(transaction=False)
        for i in ids:
            pipe.hgetall(self.key(i))
        return [Job.from_hash(h) for h in pipe.execute() if h], int(total)

    def transition(
        self,
        job: Job,
        allowed: tuple[JobStatus, ...],
        new: JobStatus,
        *,
        run_id: str = "",
        **fields: Any,
    ) -> tuple[bool, JobStatus | None]:
        """Move ``job`` to ``new`` if its status is in ``allowed`` (and, if given, its run is ``run_id``).

        Returns:
            (done, the status before; None when the job is gone).
        """
        now = repr(time.time())
        kv: dict[str, str] = {"updated_at": now, **{k: _s(v) for k, v in fields.items()}}
        if new in TERMINAL:
            kv.setdefault("finished_at", now)
        if new == JobStatus.QUEUED:
            kv.setdefault("queued_at", now)
        flat = [x for pair in kv.items() for x in pair]
        ok, before = self._transition(
            keys=self._ending_keys(job.id, job.owner),
            args=[job.id, "," + ",".join(allowed) + ",", new, run_id, now, *flat],
        )
        return bool(ok), JobStatus(before) if before else None

    def cancel(self, job: Job) -> JobStatus | None:
        """Cancel: created/queued jobs end now; a running job gets its cancel flag.

        Returns:
            The status after (None when the job is gone).
        """
        after = self._cancel(keys=self._ending_keys(job.id, job.owner), args=[job.id, repr(time.time())])
        return JobStatus(after) if after else None

    def delete(self, job: Job) -> None:
        """Forget the job and the Idempotency-Key that made it (its files are the storage's business)."""
        idem = self.r.hget(self.key(job.id), "idem_key")
        pipe = self.r.pipeline()
        if idem:
            pipe.delete(f"{self.p}:idem:{job.owner}:{idem}")
        pipe.delete(
            *(
                self.key(job.id, part)
                for part in (
                    None, "files", "partial", "uploads", "offers", "starting", "lease", "log", "webhook"
                )
            )
        )
        pipe.zrem(self._expiry, job.id)
        pipe.zrem(self._webhooks, job.id)
        pipe.zrem(self._owner_jobs(job.owner), job.id)
        pipe.srem(self._owner_open(job.owner), job.id)
        pipe.srem(self._running, job.id)
        pipe.execute()

    # -- idempotency

    def bind_idempotency_key(
        self, owner: str, key_hash: str, job_id: str, *, ttl: int, wait: float = 2.0
    ) -> IdempotentJob | None:
        """Bind an Idempotency-Key to ``job_id``, or find the job it is bound to.

        A key bound to a job whose record is not written yet (its request is still being
        handled) is waited for, up to ``wait`` seconds; a key whose job never appears (its
        creator failed or died) is taken over.

        Returns:
            None when the key is now bound to ``job_id``; else the job it was bound to, with
            the fingerprint of the request that made it.
        """
        k = f"{self.p}:idem:{owner}:{key_hash}"
        deadline = time.monotonic() + wait
        while not self.r.set(k, job_id, nx=True, ex=ttl):
            existing = self.r.get(k)
            if existing is None:
                continue
            fingerprint = self.r.hget(self.key(existing), "idem_fp")
            if fingerprint is not None:
                return IdempotentJob(job_id=existing, fingerprint=fingerprint)
            if time.monotonic() > deadline:
                self._delete_if_equal(keys=[k], args=[existing])
            else:
                time.sleep(0.05)
        return None

    def forget_idempotency(self, owner: str, key_hash: str) -> None:
        self.r.delete(f"{self.p}:idem:{owner}:{key_hash}")

    # -- files

    def files(self, job_id: str) -> dict[str, FileInfo]:
        raw = self.r.hgetall(self.key(job_id, "files"))
        out = {}
        for path, js in sorted(raw.items()):
            d = json.loads(js)
            out[path] = FileInfo(path=path, size=int(d["size"]), sha256=d["sha256"])
        return out

    def copy_files(self, source_id: str, job_id: str) -> int:
        """Record the source job's complete files as the job's (a rerun shares its capture); how many."""
        files = self.r.hgetall(self.key(source_id, "files"))
        if files:
            self.r.hset(self.key(job_id, "files"), mapping=files)
        return len(files)

    def partial_total(self, job_id: str, path: str) -> int | None:
        v = self.r.hget(self.key(job_id, "partial"), path)
        return int(v) if v is not None else None

    def partials(self, job_id: str) -> dict[str, int]:
        return {k: int(v) for k, v in self.r.hgetall(self.key(job_id, "partial")).items()}

    def set_partial(self, job_id: str, path: str, total: int) -> None:
        self.r.hset(self.key(job_id, "partial"), path, str(total))

    def clear_partial(self, job_id: str, path: str) -> None:
        self.r.hdel(self.key(job_id, "partial"), path)

    def upload_begin(self, job_id: str, token: str, *, ttl: float = 120.0) -> Gate | JobStatus:
        """Register an upload in progress; Gate.OK, or why not (GONE, STARTING, or the job's status)."""
        return _gate(
            self._upload_begin(
                keys=[self.key(job_id), self.key(job_id, "uploads"), self.key(job_id, "starting")],
                args=[token, repr(time.time() + ttl)],
            )
        )

    def upload_touch(self, job_id: str, token: str, *, ttl: float = 120.0) -> None:
        self.r.zadd(self.key(job_id, "uploads"), {token: time.time() + ttl}, xx=True)

    def upload_end(self, job_id: str, token: str) -> None:
        self.r.zrem(self.key(job_id, "uploads"), token)

    def upload_commit(self, job_id: str, token: str, info: FileInfo) -> Gate | JobStatus:
        """Record a complete file if the job still takes uploads; Gate.OK or why not."""
        return _gate(
            self._upload_commit(
                keys=[
                    self.key(job_id),
                    self.key(job_id, "files"),
                    self.key(job_id, "uploads"),
                    self.key(job_id, "partial"),
                ],
                args=[token, info.path, json.dumps({"size": info.size, "sha256": info.sha256}), repr(time.time())],
            )
        )

    def path_lock(self, job_id: str, path: str, *, timeout: float = 60.0) -> redis.lock.Lock:
        """A lock held while one upload of ``path`` is recorded and renamed into the capture."""
        name = self.key(job_id, f"lock:{hashlib.sha256(path.encode()).hexdigest()}")
        return self.r.lock(name, timeout=timeout, blocking_timeout=timeout)

    def remove_files(self, job_id: str, paths: list[str]) -> None:
        if paths:
            self.r.hdel(self.key(job_id, "files"), *paths)

    def offer_upload(self, job_id: str, upload_id: str, spec: dict[str, Any]) -> None:
        """Remember a presigned upload offered for the job (``spec`` has its ``expires_at``)."""
        self.r.hset(self.key(job_id, "offers"), upload_id, json.dumps(spec))

    def offer(self, job_id: str, upload_id: str, *, now: float | None = None) -> dict[str, Any] | None:
        """A presigned upload offered for the job, unless unknown or expired (then forgotten)."""
        raw = self.r.hget(self.key(job_id, "offers"), upload_id)
        if raw is None:
            return None
        spec: dict[str, Any] = json.loads(raw)
        if float(spec["expires_at"]) < (time.time() if now is None else now):
            self.drop_offer(job_id, upload_id)
            return None
        return spec

    def drop_offer(self, job_id: str, upload_id: str) -> None:
        self.r.hdel(self.key(job_id, "offers"), upload_id)

    def start_lock(self, job_id: str, *, ttl: int = 900) -> Gate | JobStatus:
        """Hold the job while its capture is validated; Gate.OK or why not (UPLOADING, STARTING, status)."""
        return _gate(
            self._start_lock(
                keys=[self.key(job_id), self.key(job_id, "uploads"), self.key(job_id, "starting")],
                args=[repr(time.time()), ttl],
            )
        )

    def start_unlock(self, job_id: str) -> None:
        self.r.delete(self.key(job_id, "starting"))

    # -- worker side

    def claim(
        self, job_id: str, run_id: str, *, lease_seconds: float, max_deliveries: int, task_id: str = ""
    ) -> tuple[Claim, int]:
        """A delivery of the job's task starts a run of that job.

        Returns:
            (Claim.OK, delivery number) when this run now owns the job; (GONE | DONE |
            NOT_QUEUED | BUSY, 0) when there is nothing to do; (EXHAUSTED, n) when the job
            was just failed for having killed its worker too often.
        """
        owner = self.r.hget(self.key(job_id), "owner") or ""
        what, n, _ = self._claim(
            keys=[
                self.key(job_id),
                self._running,
                self.key(job_id, "lease"),
                self._owner_open(owner),
                self._expiry,
                self._webhooks,
            ],
            args=[job_id, run_id, repr(time.time()), int(lease_seconds * 1000), max_deliveries, task_id],
        )
        return Claim(what), int(n)

    def claim_next(
        self, hint: str, run_id: str, *, lease_seconds: float, max_deliveries: int, task_id: str = ""
    ) -> tuple[Claim, str, int]:
        """A delivery of any job's task starts a run of the next job in fair order.

        The next job is the oldest ready job of the tenant served least recently; when no job
        is ready, the message's own job ``hint`` is claimed as by :meth:`claim` (a running job
        whose lease lapsed is taken over at once).

        Returns:
            (what, the job id, n) with what and n as :meth:`claim` answers them.
        """
        what, n, job_id = self._claim_next(
            keys=[f"{self.p}:ready", f"{self.p}:served", f"{self.p}:dispatch", self._running, self._expiry,
                  self._webhooks],
            args=[self.p, run_id, repr(time.time()), int(lease_seconds * 1000), max_deliveries, task_id],
        )
        if what == "empty":
            c, n = self.claim(
                hint, run_id, lease_seconds=lease_seconds, max_deliveries=max_deliveries, task_id=task_id
            )
            return c, hint, n
        return Claim(what), str(job_id), int(n)

    def running_task(self, task_id: str) -> str | None:
        """The running job that the Celery task ``task_id`` claimed, if any."""
        for job_id in self.r.smembers(self._running):
            if task_id and self.r.hget(self.key(job_id), "task_id") == task_id:
                return str(job_id)
        return None

    def heartbeat(self, job_id: str, run_id: str, *, lease_seconds: float) -> bool:
        """Extend the run's lease; False when the run no longer owns the job."""
        return bool(
            self._heartbeat(
                keys=[self.key(job_id), self.key(job_id, "lease")], args=[run_id, int(lease_seconds * 1000)]
            )
        )

    def progress(
        self, job_id: str, run_id: str, *, stage: str, fraction: float, stage_timings: dict[str, float]
    ) -> bool:
        """Record progress (kept monotonic); False when the run no longer owns the job."""
        fraction = min(max(float(fraction), 0.0), 1.0)
        return bool(
            self._progress(
                keys=[self.key(job_id)],
                args=[run_id, repr(fraction), stage, repr(time.time()), json.dumps(stage_timings)],
            )
        )

    def should_stop(self, job_id: str, run_id: str) -> bool:
        """True when the job was canceled, deleted, or taken over by another run."""
        status, cancel, current = self.r.hmget(self.key(job_id), "status", "cancel", "run_id")
        return status != JobStatus.RUNNING or cancel == "1" or current != run_id

    def finish(self, job: Job, run_id: str, status: JobStatus, **fields: Any) -> bool:
        """End the run's job with a terminal ``status``, if the run still owns it (one atomic check)."""
        if not run_id:
            raise ValueError("finish needs the run id")
        ok, _ = self.transition(job, (JobStatus.RUNNING,), status, run_id=run_id, **fields)
        return ok

    def lapsed_running(self) -> list[str]:
        """Jobs marked running whose worker stopped renewing the lease."""
        ids = list(self.r.smembers(self._running))
        if not ids:
            return []
        pipe = self.r.pipeline(transaction=False)
        for i in ids:
            pipe.exists(self.key(i, "lease"))
        return [i for i, alive in zip(ids, pipe.execute(), strict=True) if not alive]

    def requeue_lapsed(self, job_id: str) -> bool:
        """Put a running job whose lease lapsed back to queued, first of its tenant's (one caller wins)."""
        owner = self.r.hget(self.key(job_id), "owner") or ""
        return bool(
            self._requeue(
                keys=[self.key(job_id), self._running, self.key(job_id, "lease"), *self._ready_keys(owner)],
                args=[job_id, repr(time.time())],
            )
        )

    # -- retention, webhooks, workers

    def expired(self, *, now: float, limit: int = 100) -> list[str]:
        """Finished jobs whose ttl ran out by ``now`` (oldest first)."""
        return list(self.r.zrangebyscore(self._expiry, "-inf", now, start=0, num=limit))

    def delete_expiry(self, job_id: str) -> None:
        self.r.zrem(self._expiry, job_id)

    def due_webhooks(self, *, now: float, limit: int = 20) -> list[str]:
        """Jobs whose webhook event is due by ``now``."""
        return list(self.r.zrangebyscore(self._webhooks, "-inf", now, start=0, num=limit))

    def take_webhook(self, job_id: str) -> bool:
        """Claim a due webhook event (one caller among all workers wins)."""
        return bool(self.r.zrem(self._webhooks, job_id))

    def retry_webhook(self, job_id: str, *, at: float) -> None:
        self.r.zadd(self._webhooks, {job_id: at})

    def record_delivery(self, job_id: str, attempt: dict[str, Any]) -> int:
        """Append a delivery attempt to the job's webhook record; returns how many there are."""
        return int(self.r.rpush(self.key(job_id, "webhook"), json.dumps(attempt)))

    def deliveries(self, job_id: str) -> list[dict[str, Any]]:
        return [json.loads(x) for x in self.r.lrange(self.key(job_id, "webhook"), 0, 99)]

    def worker_seen(self, name: str, info: dict[str, Any], *, ttl: float) -> None:
        """A worker's heartbeat: its self-description, kept ``ttl`` seconds."""
        self.r.set(f"{self.p}:worker:{name}", json.dumps(info), px=int(ttl * 1000))

    def workers(self) -> list[dict[str, Any]]:
        """The live workers' self-descriptions."""
        keys = list(self.r.scan_iter(match=f"{self.p}:worker:*", count=100))
        values = self.r.mget(keys) if keys else []
        return [json.loads(v) for v in values if v]

    def queue_length(self, queue: str) -> int:
        """Messages waiting in a Celery queue on this Redis (every priority list of kombu's transport)."""
        names = [queue, *(f"{queue}\x06\x16{p}" for p in (3, 6, 9))]
        pipe = self.r.pipeline(transaction=False)
        for n in names:
            pipe.llen(n)
        return int(sum(pipe.execute()))

    def abandoned(self, *, older_than: float, now: float | None = None) -> list[Job]:
        """Created jobs untouched for ``older_than`` seconds with no upload in progress."""
        cutoff = (time.time() if now is None else now) - older_than
        found = []
        for open_key in self.r.scan_iter(match=f"{self.p}:owner:*:open", count=500):
            for job_id in self.r.smembers(open_key):
                job = self.get(job_id)
                if (
                    job is not None
                    and job.status is JobStatus.CREATED
                    and job.updated_at < cutoff
                    and not self.r.zcount(self.key(job_id, "uploads"), now or time.time(), "+inf")
                ):
                    found.append(job)
        return found

    # -- validation (off the request path)

    def validating_begin(self, job_id: str) -> None:
        """Note that ``job_id``'s capture is being validated (its validation's start time)."""
        self.r.zadd(f"{self.p}:validating", {job_id: time.time()})

    def validating_end(self, job_id: str) -> None:
        self.r.zrem(f"{self.p}:validating", job_id)

    def stale_validating(self, *, older_than: float, now: float | None = None) -> list[str]:
        """Jobs whose validation started more than ``older_than`` seconds ago (its API process died)."""
        cutoff = (time.time() if now is None else now) - older_than
        return list(self.r.zrangebyscore(f"{self.p}:validating", "-inf", cutoff, start=0, num=100))

    # -- log

    def log(self, job_id: str, message: str, *, max_lines: int = 10_000) -> None:
        key = self.key(job_id, "log")
        if self.r.llen(key) < max_lines:
            self.r.rpush(key, json.dumps({"t": time.time(), "msg": message}))

    def read_log(self, job_id: str, since: int, limit: int) -> tuple[list[dict[str, Any]], int]:
        """Log lines [since, since + limit) as dicts {"t", "msg"}, and the total line count."""
        key = self.key(job_id, "log")
        pipe = self.r.pipeline(transaction=False)
        pipe.lrange(key, since, since + limit - 1)
        pipe.llen(key)
        lines, total = pipe.execute()
        return [json.loads(x) for x in lines], int(total)


def _s(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, bool):
        return "1" if v else "0"
    if isinstance(v, (dict, list)):
        return json.dumps(v)
    if isinstance(v, float):
        return repr(v)
    return str(v)
