"""The job store's Lua scripts: every state change that depends on the current state.

Each script runs atomically in Redis, so concurrent API processes and workers
never interleave a check and a write. The status names are
:class:`service.store.JobStatus` values; the gate answers ('ok', 'gone',
'uploading', 'starting') are :class:`service.store.Gate` values.

A job that ends (succeeded, failed, canceled) is, in the same script
(:data:`_ENDED`), scheduled for deletion in the expiry zset when it has a
``ttl``, and for a webhook delivery in the webhooks zset when it has a
``callback_url``.
"""

_ENDED = """
local function ended(job, id, now, expiry, webhooks)
  local ttl = tonumber(redis.call('HGET', job, 'ttl') or '0') or 0
  if ttl > 0 then redis.call('ZADD', expiry, tonumber(now) + ttl, id) end
  local url = redis.call('HGET', job, 'callback_url')
  if url and url ~= '' then redis.call('ZADD', webhooks, now, id) end
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

TRANSITION = _ENDED + """
-- KEYS: job, owner open, running, lease, expiry, webhooks
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
end
return {1, st}
"""

CLAIM = _ENDED + """
-- KEYS: job, running, lease, owner open, expiry, webhooks; ARGV: id, run id, now, lease ms, max deliveries
local st = redis.call('HGET', KEYS[1], 'status')
if not st then return {'gone', 0} end
if st == 'succeeded' or st == 'failed' or st == 'canceled' then return {'done', 0} end
if st == 'created' or st == 'validating' then return {'not_queued', 0} end
if st == 'running' and redis.call('EXISTS', KEYS[3]) == 1 then return {'busy', 0} end
local n = redis.call('HINCRBY', KEYS[1], 'deliveries', 1)
if n > tonumber(ARGV[5]) then
  redis.call('HSET', KEYS[1], 'status', 'failed', 'finished_at', ARGV[3], 'updated_at', ARGV[3],
    'error', 'the job was started ' .. (n - 1) .. ' times and its worker died each time; giving up')
  redis.call('SREM', KEYS[2], ARGV[1]); redis.call('SREM', KEYS[4], ARGV[1])
  ended(KEYS[1], ARGV[1], ARGV[3], KEYS[5], KEYS[6])
  return {'exhausted', n}
end
redis.call('HSET', KEYS[1], 'status', 'running', 'run_id', ARGV[2], 'updated_at', ARGV[3])
redis.call('HSETNX', KEYS[1], 'started_at', ARGV[3])
redis.call('SADD', KEYS[2], ARGV[1])
redis.call('SET', KEYS[3], ARGV[2], 'PX', ARGV[4])
return {'ok', n}
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

REQUEUE = """
-- KEYS: job, running, lease; ARGV: id, now
local st = redis.call('HGET', KEYS[1], 'status')
if st ~= 'running' then redis.call('SREM', KEYS[2], ARGV[1]); return 0 end
if redis.call('EXISTS', KEYS[3]) == 1 then return 0 end
redis.call('HSET', KEYS[1], 'status', 'queued', 'run_id', '', 'updated_at', ARGV[2])
redis.call('SREM', KEYS[2], ARGV[1])
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
