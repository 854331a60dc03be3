"""Job state in Redis, under the service's own keys (not Celery's result backend).

Keys (``P`` is ``Settings.key_prefix``)::

    P:job:<id>             hash: status, stage, progress, options, owner, times, error, run_id, ...
    P:job:<id>:files       hash: capture path -> {"size", "sha256"} of every complete upload
    P:job:<id>:partial     hash: capture path -> total size declared by Content-Range
    P:job:<id>:uploads     zset: upload tokens in progress, scored by their expiry time
    P:job:<id>:starting    string with a TTL: held while POST /start validates the capture
    P:job:<id>:lease       string with a TTL: the run id of the worker running the job (heartbeat)
    P:job:<id>:log         list of JSON lines {"t", "msg"}
    P:owner:<owner>:jobs   zset: the owner's job ids by creation time
    P:owner:<owner>:open   set: the owner's unfinished jobs (created, queued, running)
    P:running              set: jobs in status running (scanned for lapsed leases)
    P:idem:<owner>:<hash>  string with a TTL: Idempotency-Key -> job id

Every state change that depends on the current state is one Lua script, so
concurrent API processes and workers never interleave a check and a write.
Progress only grows; a worker's writes count only while its run id is the
job's current one (a stale, superseded run changes nothing).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from typing import Any

import redis

STATUSES = ("created", "queued", "running", "succeeded", "failed", "canceled")
TERMINAL = frozenset({"succeeded", "failed", "canceled"})

_SCRIPT_CREATE = """
-- KEYS: job, owner jobs, owner open; ARGV: id, limit, created_at, field/value pairs...
if redis.call('EXISTS', KEYS[1]) == 1 then return -1 end
local n = redis.call('SCARD', KEYS[3])
if n >= tonumber(ARGV[2]) then return n end
redis.call('HSET', KEYS[1], unpack(ARGV, 4))
redis.call('ZADD', KEYS[2], ARGV[3], ARGV[1])
redis.call('SADD', KEYS[3], ARGV[1])
return -2
"""

_SCRIPT_TRANSITION = """
-- KEYS: job, owner open, running, lease
-- ARGV: id, allowed (',a,b,'), new status, run id required ('' for any), field/value pairs...
local st = redis.call('HGET', KEYS[1], 'status')
if not st then return {0, ''} end
if not string.find(ARGV[2], ',' .. st .. ',', 1, true) then return {0, st} end
if ARGV[4] ~= '' and redis.call('HGET', KEYS[1], 'run_id') ~= ARGV[4] then return {0, st} end
redis.call('HSET', KEYS[1], 'status', ARGV[3], unpack(ARGV, 5))
local new = ARGV[3]
if new == 'succeeded' or new == 'failed' or new == 'canceled' then
  redis.call('SREM', KEYS[2], ARGV[1]); redis.call('SREM', KEYS[3], ARGV[1]); redis.call('DEL', KEYS[4])
elseif new == 'queued' then
  redis.call('SREM', KEYS[3], ARGV[1])
end
return {1, st}
"""

_SCRIPT_CLAIM = """
-- KEYS: job, running, lease, owner open; ARGV: id, run id, now, lease ms, max deliveries
local st = redis.call('HGET', KEYS[1], 'status')
if not st then return {'gone', 0} end
if st == 'succeeded' or st == 'failed' or st == 'canceled' then return {'done', 0} end
if st == 'created' then return {'not_queued', 0} end
if st == 'running' and redis.call('EXISTS', KEYS[3]) == 1 then return {'busy', 0} end
local n = redis.call('HINCRBY', KEYS[1], 'deliveries', 1)
if n > tonumber(ARGV[5]) then
  redis.call('HSET', KEYS[1], 'status', 'failed', 'finished_at', ARGV[3], 'updated_at', ARGV[3],
    'error', 'the job was started ' .. (n - 1) .. ' times and its worker died each time; giving up')
  redis.call('SREM', KEYS[2], ARGV[1]); redis.call('SREM', KEYS[4], ARGV[1])
  return {'exhausted', n}
end
redis.call('HSET', KEYS[1], 'status', 'running', 'run_id', ARGV[2], 'updated_at', ARGV[3])
redis.call('HSETNX', KEYS[1], 'started_at', ARGV[3])
redis.call('SADD', KEYS[2], ARGV[1])
redis.call('SET', KEYS[3], ARGV[2], 'PX', ARGV[4])
return {'ok', n}
"""

_SCRIPT_HEARTBEAT = """
-- KEYS: job, lease; ARGV: run id, lease ms
if redis.call('HGET', KEYS[1], 'run_id') ~= ARGV[1] then return 0 end
if redis.call('HGET', KEYS[1], 'status') ~= 'running' then return 0 end
redis.call('SET', KEYS[2], ARGV[1], 'PX', ARGV[2])
return 1
"""

_SCRIPT_PROGRESS = """
-- KEYS: job; ARGV: run id, fraction, stage, now, stage timings json
if redis.call('HGET', KEYS[1], 'run_id') ~= ARGV[1] then return 0 end
if redis.call('HGET', KEYS[1], 'status') ~= 'running' then return 0 end
local old = tonumber(redis.call('HGET', KEYS[1], 'progress') or '0') or 0
local new = tonumber(ARGV[2])
if new > old then redis.call('HSET', KEYS[1], 'progress', ARGV[2]) end
redis.call('HSET', KEYS[1], 'stage', ARGV[3], 'updated_at', ARGV[4], 'stage_timings', ARGV[5])
return 1
"""

_SCRIPT_REQUEUE = """
-- KEYS: job, running, lease; ARGV: id, now
local st = redis.call('HGET', KEYS[1], 'status')
if st ~= 'running' then redis.call('SREM', KEYS[2], ARGV[1]); return 0 end
if redis.call('EXISTS', KEYS[3]) == 1 then return 0 end
redis.call('HSET', KEYS[1], 'status', 'queued', 'run_id', '', 'updated_at', ARGV[2])
redis.call('SREM', KEYS[2], ARGV[1])
return 1
"""

_SCRIPT_UPLOAD_BEGIN = """
-- KEYS: job, uploads, starting; ARGV: token, expiry
local st = redis.call('HGET', KEYS[1], 'status')
if not st then return 'gone' end
if st ~= 'created' then return st end
if redis.call('EXISTS', KEYS[3]) == 1 then return 'starting' end
redis.call('ZADD', KEYS[2], ARGV[2], ARGV[1])
return 'ok'
"""

_SCRIPT_UPLOAD_COMMIT = """
-- KEYS: job, files, uploads, partial; ARGV: token, path, info json
redis.call('ZREM', KEYS[3], ARGV[1])
local st = redis.call('HGET', KEYS[1], 'status')
if st ~= 'created' then return st or 'gone' end
redis.call('HSET', KEYS[2], ARGV[2], ARGV[3])
redis.call('HDEL', KEYS[4], ARGV[2])
return 'ok'
"""

_SCRIPT_START_LOCK = """
-- KEYS: job, uploads, starting; ARGV: now, ttl s
local st = redis.call('HGET', KEYS[1], 'status')
if not st then return 'gone' end
if st ~= 'created' then return st end
redis.call('ZREMRANGEBYSCORE', KEYS[2], '-inf', ARGV[1])
if redis.call('ZCARD', KEYS[2]) > 0 then return 'uploading' end
if not redis.call('SET', KEYS[3], '1', 'NX', 'EX', ARGV[2]) then return 'starting' end
return 'ok'
"""

_SCRIPT_CANCEL = """
-- KEYS: job, owner open, running, lease; ARGV: id, now
local st = redis.call('HGET', KEYS[1], 'status')
if not st then return '' end
if st == 'created' or st == 'queued' then
  redis.call('HSET', KEYS[1], 'status', 'canceled', 'cancel', '1',
    'finished_at', ARGV[2], 'updated_at', ARGV[2])
  redis.call('SREM', KEYS[2], ARGV[1]); redis.call('SREM', KEYS[3], ARGV[1]); redis.call('DEL', KEYS[4])
  return 'canceled'
end
if st == 'running' then redis.call('HSET', KEYS[1], 'cancel', '1', 'updated_at', ARGV[2]) end
return st
"""


@dataclass(frozen=True)
class FileInfo:
    """A complete capture file of a job."""

    path: str
    size: int
    sha256: str


@dataclass
class Job:
    """A job as stored (times are Unix seconds)."""

    id: str
    owner: str
    status: str
    options: dict[str, Any]
    created_at: float
    updated_at: float
    label: str | None = None
    stage: str | None = None
    progress: float = 0.0
    queued_at: float | None = None
    started_at: float | None = None
    finished_at: float | None = None
    error: str | None = None
    cancel_requested: bool = False
    deliveries: int = 0
    run_id: str = ""
    stage_timings: dict[str, float] = field(default_factory=dict)

    @classmethod
    def from_hash(cls, h: dict[str, str]) -> Job:
        def opt_float(name: str) -> float | None:
            v = h.get(name)
            return float(v) if v not in (None, "") else None

        return cls(
            id=h["id"],
            owner=h["owner"],
            status=h["status"],
            options=json.loads(h.get("options") or "{}"),
            created_at=float(h["created_at"]),
            updated_at=float(h.get("updated_at") or h["created_at"]),
            label=h.get("label") or None,
            stage=h.get("stage") or None,
            progress=float(h.get("progress") or 0.0),
            queued_at=opt_float("queued_at"),
            started_at=opt_float("started_at"),
            finished_at=opt_float("finished_at"),
            error=h.get("error") or None,
            cancel_requested=h.get("cancel") == "1",
            deliveries=int(h.get("deliveries") or 0),
            run_id=h.get("run_id") or "",
            stage_timings=json.loads(h.get("stage_timings") or "{}"),
        )


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
        self._create = client.register_script(_SCRIPT_CREATE)
        self._transition = client.register_script(_SCRIPT_TRANSITION)
        self._claim = client.register_script(_SCRIPT_CLAIM)
        self._heartbeat = client.register_script(_SCRIPT_HEARTBEAT)
        self._progress = client.register_script(_SCRIPT_PROGRESS)
        self._requeue = client.register_script(_SCRIPT_REQUEUE)
        self._upload_begin = client.register_script(_SCRIPT_UPLOAD_BEGIN)
        self._upload_commit = client.register_script(_SCRIPT_UPLOAD_COMMIT)
        self._start_lock = client.register_script(_SCRIPT_START_LOCK)
        self._cancel = client.register_script(_SCRIPT_CANCEL)

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
            "status": "created",
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
        self, job: Job, allowed: tuple[str, ...], new: str, *, run_id: str = "", **fields: Any
    ) -> tuple[bool, str]:
        """Move ``job`` to ``new`` if its status is in ``allowed`` (and, if given, its run is ``run_id``).

        Returns:
            (done, the status before).
        """
        now = repr(time.time())
        kv: dict[str, str] = {"updated_at": now, **{k: _s(v) for k, v in fields.items()}}
        if new in TERMINAL:
            kv.setdefault("finished_at", now)
        if new == "queued":
            kv.setdefault("queued_at", now)
        flat = [x for pair in kv.items() for x in pair]
        ok, before = self._transition(
            keys=[self.key(job.id), self._owner_open(job.owner), self._running, self.key(job.id, "lease")],
            args=[job.id, "," + ",".join(allowed) + ",", new, run_id, *flat],
        )
        return bool(ok), before

    def cancel(self, job: Job) -> str:
        """Cancel: created/queued jobs end now; a running job gets its cancel flag.

        Returns:
            The status after ('' when the job is gone).
        """
        return self._cancel(
            keys=[self.key(job.id), self._owner_open(job.owner), self._running, self.key(job.id, "lease")],
            args=[job.id, repr(time.time())],
        )

    def delete(self, job: Job) -> None:
        """Forget the job and the Idempotency-Key that made it (its files are the storage's business)."""
        idem = self.r.hget(self.key(job.id), "idem_key")
        pipe = self.r.pipeline()
        if idem:
            pipe.delete(f"{self.p}:idem:{job.owner}:{idem}")
        pipe.delete(
            *(
                self.key(job.id, part)
                for part in (None, "files", "partial", "uploads", "starting", "lease", "log")
            )
        )
        pipe.zrem(self._owner_jobs(job.owner), job.id)
        pipe.srem(self._owner_open(job.owner), job.id)
        pipe.srem(self._running, job.id)
        pipe.execute()

    # -- idempotency

    def idempotent_job(self, owner: str, key_hash: str, job_id: str, ttl: int) -> str | None:
        """Bind an Idempotency-Key to ``job_id``; returns the job id it was already bound to, or None."""
        k = f"{self.p}:idem:{owner}:{key_hash}"
        if self.r.set(k, job_id, nx=True, ex=ttl):
            return None
        return self.r.get(k)

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

    def partial_total(self, job_id: str, path: str) -> int | None:
        v = self.r.hget(self.key(job_id, "partial"), path)
        return int(v) if v is not None else None

    def partials(self, job_id: str) -> dict[str, int]:
        return {k: int(v) for k, v in self.r.hgetall(self.key(job_id, "partial")).items()}

    def set_partial(self, job_id: str, path: str, total: int) -> None:
        self.r.hset(self.key(job_id, "partial"), path, str(total))

    def clear_partial(self, job_id: str, path: str) -> None:
        self.r.hdel(self.key(job_id, "partial"), path)

    def upload_begin(self, job_id: str, token: str, *, ttl: float = 120.0) -> str:
        """Register an upload in progress; 'ok', or why not ('gone', 'starting', or the job's status)."""
        return self._upload_begin(
            keys=[self.key(job_id), self.key(job_id, "uploads"), self.key(job_id, "starting")],
            args=[token, repr(time.time() + ttl)],
        )

    def upload_touch(self, job_id: str, token: str, *, ttl: float = 120.0) -> None:
        self.r.zadd(self.key(job_id, "uploads"), {token: time.time() + ttl}, xx=True)

    def upload_end(self, job_id: str, token: str) -> None:
        self.r.zrem(self.key(job_id, "uploads"), token)

    def upload_commit(self, job_id: str, token: str, info: FileInfo) -> str:
        """Record a complete file if the job still takes uploads; 'ok' or why not."""
        return self._upload_commit(
            keys=[
                self.key(job_id),
                self.key(job_id, "files"),
                self.key(job_id, "uploads"),
                self.key(job_id, "partial"),
            ],
            args=[token, info.path, json.dumps({"size": info.size, "sha256": info.sha256})],
        )

    def remove_files(self, job_id: str, paths: list[str]) -> None:
        if paths:
            self.r.hdel(self.key(job_id, "files"), *paths)

    def start_lock(self, job_id: str, *, ttl: int = 900) -> str:
        """Hold the job while its capture is validated; 'ok' or why not ('uploading', 'starting', status)."""
        return self._start_lock(
            keys=[self.key(job_id), self.key(job_id, "uploads"), self.key(job_id, "starting")],
            args=[repr(time.time()), ttl],
        )

    def start_unlock(self, job_id: str) -> None:
        self.r.delete(self.key(job_id, "starting"))

    # -- worker side

    def claim(
        self, job_id: str, run_id: str, *, lease_seconds: float, max_deliveries: int
    ) -> tuple[str, int]:
        """A delivery of the job's task starts a run.

        Returns:
            ('ok', delivery number) when this run now owns the job; ('gone' | 'done' |
            'not_queued' | 'busy', 0) when there is nothing to do; ('exhausted', n) when the job
            was just failed for having killed its worker too often.
        """
        job = self.r.hget(self.key(job_id), "owner") or ""
        what, n = self._claim(
            keys=[self.key(job_id), self._running, self.key(job_id, "lease"), self._owner_open(job)],
            args=[job_id, run_id, repr(time.time()), int(lease_seconds * 1000), max_deliveries],
        )
        return what, int(n)

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
        return status != "running" or cancel == "1" or current != run_id

    def finish(self, job: Job, run_id: str, status: str, **fields: Any) -> bool:
        """End the run's job with a terminal ``status``, if the run still owns it (one atomic check)."""
        if not run_id:
            raise ValueError("finish needs the run id")
        ok, _ = self.transition(job, ("running",), status, run_id=run_id, **fields)
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
        """Put a running job whose lease lapsed back to queued (one caller wins)."""
        return bool(
            self._requeue(
                keys=[self.key(job_id), self._running, self.key(job_id, "lease")],
                args=[job_id, repr(time.time())],
            )
        )

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
