"""The job store's Lua scripts: every state change that depends on the current state.

Each script runs atomically in Redis, so concurrent API processes and workers
never interleave a check and a write. The status names are
:class:`service.store.JobStatus` values; the gate answers ('ok', 'gone',
'uploading', 'starting') are :class:`service.store.Gate` values.

A job that ends (succeeded, failed, canceled) is, in the same script
(:data:`_ENDED`), scheduled for deletion in the expiry zset when it has a
``ttl``, and for a webhook delivery in the webhooks zset when it has a
``callback_url``.

A job that becomes queued is, in the same script (:data:`_READY`), appended to
its tenant's ready list, and the tenant joins the ready zset scored by when it
was last served; :data:`CLAIM_NEXT` takes the next job of the least recently
served tenant (fair dispatch). Entries of jobs that left ``queued`` another way
(canceled, deleted, sent back to created) stay in the lists and are skipped.
"""

_ENDED = """
local function ended(job, id, now, expiry, webhooks)
  local ttl = tonumber(redis.call('HGET', job, 'ttl') or '0') or 0
  if ttl > 0 then redis.call('ZADD', expiry, tonumber(now) + ttl, id) end
  local url = redis.call('HGET', job, 'callback_url')
  if url and url ~= '' then redis.call('ZADD', webhooks, now, id) end
end
"""

_READY = """
local function ready(list, tenants, served, owner, id, front)
  if front then redis.call('LPUSH', list, id) else redis.call('RPUSH', list, id) end
  if not redis.call('ZSCORE', tenants, owner) then
    redis.call('ZADD', tenants, tonumber(redis.call('HGET', served, owner) or '0') or 0, owner)
  end
end
"""

_TAKE = """
local function take(job, id, running, lease, open, expiry, webhooks, run_id, now, lease_ms, max_deliveries, task)
  local n = redis.call('HINCRBY', job, 'deliveries', 1)
  if n > tonumber(max_deliveries) then
    redis.call('HSET', job, 'status', 'failed', 'finished_at', now, 'updated_at', now,
      'error', 'the job was started ' .. (n - 1) .. ' times and its worker died each time; giving up')
    redis.call('SREM', running, id); redis.call('SREM', open, id)
    ended(job, id, now, expiry, webhooks)
    return {'exhausted', n, id}
  end
  redis.call('HSET', job, 'status', 'running', 'run_id', run_id, 'task_id', task, 'updated_at', now)
  redis.call('HSETNX', job, 'started_at', now)
  redis.call('SADD', running, id)
  redis.call('SET', lease, run_id, 'PX', lease_ms)
  return {'ok', n, id}
end
"""

CREATE = """
-- KEYS: job, owner jobs, owner open; ARGV: id, limit, created_at, field/value pairs...
if redis.call('EXISTS', KEYS[1]) == 1 then return -1 end
local n = redis.call('SCARD', KEYS[3])
if n >= tonumber(ARGV[2]) then return n end
redis.call('HSET', KEYS[1], unpack(ARGV, 4))
redis.call('ZADD', KEYS[2], ARGV[3], ARGV[1])
redis.call('SADD', KEYS[3], ARGV[1])
return -2
"""

TRANSITION = _ENDED + _READY + """
-- KEYS: job, owner open, running, lease, expiry, webhooks, owner ready, ready tenants, served
-- ARGV: id, allowed (',a,b,'), new status, run id required ('' for any), now, field/value pairs...
local st = redis.call('HGET', KEYS[1], 'status')
if not st then return {0, ''} end
if not string.find(ARGV[2], ',' .. st .. ',', 1, true) then return {0, st} end
if ARGV[4] ~= '' and redis.call('HGET', KEYS[1], 'run_id') ~= ARGV[4] then return {0, st} end
redis.call('HSET', KEYS[1], 'status', ARGV[3], unpack(ARGV, 6))
local new = ARGV[3]
if new == 'succeeded' or new == 'failed' or new == 'canceled' then
  redis.call('SREM', KEYS[2], ARGV[1]); redis.call('SREM', KEYS[3], ARGV[1]); redis.call('DEL', KEYS[4])
  ended(KEYS[1], ARGV[1], ARGV[5], KEYS[5], KEYS[6])
elseif new == 'queued' then
  redis.call('SREM', KEYS[3], ARGV[1])
  ready(KEYS[7], KEYS[8], KEYS[9], redis.call('HGET', KEYS[1], 'owner'), ARGV[1], false)
end
return {1, st}
"""

CLAIM = _ENDED + _TAKE + """
-- KEYS: job, running, lease, owner open, expiry, webhooks
-- ARGV: id, run id, now, lease ms, max deliveries, task id
local st = redis.call('HGET', KEYS[1], 'status')
if not st then return {'gone', 0, ARGV[1]} end
if st == 'succeeded' or st == 'failed' or st == 'canceled' then return {'done', 0, ARGV[1]} end
if st == 'created' or st == 'validating' then return {'not_queued', 0, ARGV[1]} end
if st == 'running' and redis.call('EXISTS', KEYS[3]) == 1 then return {'busy', 0, ARGV[1]} end
return take(KEYS[1], ARGV[1], KEYS[2], KEYS[3], KEYS[4], KEYS[5], KEYS[6],
  ARGV[2], ARGV[3], ARGV[4], ARGV[5], ARGV[6])
"""

CLAIM_NEXT = _ENDED + _TAKE + """
-- KEYS: ready tenants, served, dispatch counter, running, expiry, webhooks
-- ARGV: key prefix, run id, now, lease ms, max deliveries, task id
-- The tenant served least recently (lowest score; never served: 0) gives its oldest ready job.
while true do
  local first = redis.call('ZRANGE', KEYS[1], 0, 0)
  if #first == 0 then return {'empty', 0, ''} end
  local owner = first[1]
  local list = ARGV[1] .. ':ready:' .. owner
  local id = redis.call('LPOP', list)
  local more = redis.call('LLEN', list) > 0
  if not more then redis.call('ZREM', KEYS[1], owner) end
  local job = ARGV[1] .. ':job:' .. (id or '')
  if id and redis.call('HGET', job, 'status') == 'queued' then
    local seq = redis.call('INCR', KEYS[3])
    redis.call('HSET', KEYS[2], owner, seq)
    if more then redis.call('ZADD', KEYS[1], seq, owner) end
    return take(job, id, KEYS[4], job .. ':lease', ARGV[1] .. ':owner:' .. owner .. ':open', KEYS[5], KEYS[6],
      ARGV[2], ARGV[3], ARGV[4], ARGV[5], ARGV[6])
  end
end
"""

HEARTBEAT = """
-- KEYS: job, lease; ARGV: run id, lease ms
if redis.call('HGET', KEYS[1], 'run_id') ~= ARGV[1] then return 0 end
if redis.call('HGET', KEYS[1], 'status') ~= 'running' then return 0 end
redis.call('SET', KEYS[2], ARGV[1], 'PX', ARGV[2])
return 1
"""

PROGRESS = """
-- KEYS: job; ARGV: run id, fraction, stage, now, stage timings json
if redis.call('HGET', KEYS[1], 'run_id') ~= ARGV[1] then return 0 end
if redis.call('HGET', KEYS[1], 'status') ~= 'running' then return 0 end
local old = tonumber(redis.call('HGET', KEYS[1], 'progress') or '0') or 0
local new = tonumber(ARGV[2])
if new > old then redis.call('HSET', KEYS[1], 'progress', ARGV[2]) end
redis.call('HSET', KEYS[1], 'stage', ARGV[3], 'updated_at', ARGV[4], 'stage_timings', ARGV[5])
return 1
"""

REQUEUE = _READY + """
-- KEYS: job, running, lease, owner ready, ready tenants, served; ARGV: id, now
-- The job goes to the front of its tenant's ready list: it was dispatched once already.
local st = redis.call('HGET', KEYS[1], 'status')
if st ~= 'running' then redis.call('SREM', KEYS[2], ARGV[1]); return 0 end
if redis.call('EXISTS', KEYS[3]) == 1 then return 0 end
redis.call('HSET', KEYS[1], 'status', 'queued', 'run_id', '', 'updated_at', ARGV[2])
redis.call('SREM', KEYS[2], ARGV[1])
ready(KEYS[4], KEYS[5], KEYS[6], redis.call('HGET', KEYS[1], 'owner'), ARGV[1], true)
return 1
"""

UPLOAD_BEGIN = """
-- KEYS: job, uploads, starting; ARGV: token, expiry
local st = redis.call('HGET', KEYS[1], 'status')
if not st then return 'gone' end
if st ~= 'created' then return st end
if redis.call('EXISTS', KEYS[3]) == 1 then return 'starting' end
redis.call('ZADD', KEYS[2], ARGV[2], ARGV[1])
return 'ok'
"""

UPLOAD_COMMIT = """
-- KEYS: job, files, uploads, partial; ARGV: token, path, info json, now
redis.call('ZREM', KEYS[3], ARGV[1])
local st = redis.call('HGET', KEYS[1], 'status')
if st ~= 'created' then return st or 'gone' end
redis.call('HSET', KEYS[2], ARGV[2], ARGV[3])
redis.call('HSET', KEYS[1], 'updated_at', ARGV[4])
redis.call('HDEL', KEYS[4], ARGV[2])
return 'ok'
"""

START_LOCK = """
-- KEYS: job, uploads, starting; ARGV: now, ttl s
local st = redis.call('HGET', KEYS[1], 'status')
if not st then return 'gone' end
if st ~= 'created' then return st end
redis.call('ZREMRANGEBYSCORE', KEYS[2], '-inf', ARGV[1])
if redis.call('ZCARD', KEYS[2]) > 0 then return 'uploading' end
if not redis.call('SET', KEYS[3], '1', 'NX', 'EX', ARGV[2]) then return 'starting' end
return 'ok'
"""

CANCEL = _ENDED + """
-- KEYS: job, owner open, running, lease, expiry, webhooks; ARGV: id, now
local st = redis.call('HGET', KEYS[1], 'status')
if not st then return '' end
if st == 'created' or st == 'validating' or st == 'queued' then
  redis.call('HSET', KEYS[1], 'status', 'canceled', 'cancel', '1',
    'finished_at', ARGV[2], 'updated_at', ARGV[2])
  redis.call('SREM', KEYS[2], ARGV[1]); redis.call('SREM', KEYS[3], ARGV[1]); redis.call('DEL', KEYS[4])
  ended(KEYS[1], ARGV[1], ARGV[2], KEYS[5], KEYS[6])
  return 'canceled'
end
if st == 'running' then redis.call('HSET', KEYS[1], 'cancel', '1', 'updated_at', ARGV[2]) end
return st
"""

DELETE_IF_EQUAL = """
-- KEYS: key; ARGV: expected value. Deletes the key only while it still holds that value.
if redis.call('GET', KEYS[1]) == ARGV[1] then return redis.call('DEL', KEYS[1]) end
return 0
"""
