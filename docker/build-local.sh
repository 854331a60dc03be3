#!/usr/bin/env bash
# Build and run the service's Docker image where no registry serves base images (not part of `make test`).
#
#   1. a Debian bookworm root file system made with debootstrap, imported as pmvir-base:bookworm;
#   2. pmvir's image on it (docker/Dockerfile, BASE_IMAGE=pmvir-base:bookworm), from docker/requirements.lock;
#   3. a Redis image on the same base (pmvir-redis:local);
#   4. the compose stack (Redis with its append-only file, the API, two workers), up;
#   5. a small synthetic capture pushed through with the client (`pmvir submit`), its result checked;
#   6. the stack torn down (containers, network, volumes).
#
# Needs root, docker (with a running dockerd), docker-compose and debootstrap. Settings (environment):
#   MIRROR       Debian mirror (default http://deb.debian.org/debian)
#   TORCH_INDEX  index with the CPU torch wheel (default https://download.pytorch.org/whl/cpu)
#   WHEELS       a local folder of wheels served to the build (find-links), e.g. /opt/wheels, for
#                machines that reach PyPI but not the torch index
#   PMVIR        the pmvir command of the client (default: pmvir)
#   HOST_CA      a CA bundle the images must trust (and pip use), e.g. /etc/ssl/certs/ca-certificates.crt
#                behind an intercepting proxy
set -euo pipefail
cd "$(dirname "$0")/.."

MIRROR=${MIRROR:-http://deb.debian.org/debian}
TORCH_INDEX=${TORCH_INDEX:-https://download.pytorch.org/whl/cpu}
PMVIR=${PMVIR:-pmvir}  # may be a command with arguments (word-split)
BASE=pmvir-base:bookworm
KEY=build-local-key
PORT=${PORT:-18000}
WORK=$(mktemp -d)
COMPOSE=(docker-compose -p pmvir-local -f docker/compose.yaml -f docker/compose.local.yaml)
SERVER_PID=""

cleanup() {
    echo "== teardown"
    PMVIR_API_KEYS=$KEY PMVIR_PORT=$PORT "${COMPOSE[@]}" down -v --remove-orphans || true
    [ -n "$SERVER_PID" ] && kill "$SERVER_PID" 2>/dev/null || true
    rm -rf "$WORK"
}
trap cleanup EXIT

step() { echo "== $* ($(date -u +%H:%M:%S))"; }

if ! docker image inspect "$BASE" >/dev/null 2>&1; then
    step "debootstrap bookworm -> $BASE"
    debootstrap --variant=minbase --include=python3,python3-venv,ca-certificates \
        bookworm "$WORK/rootfs" "$MIRROR" >"$WORK/debootstrap.log"
    echo "deb $MIRROR bookworm main" >"$WORK/rootfs/etc/apt/sources.list"
    tar -C "$WORK/rootfs" -c . | docker import \
        -c 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
        -c 'ENV LANG=C.UTF-8' - "$BASE"
fi

if [ -n "${HOST_CA:-}" ]; then
    step "trusting $HOST_CA in ${BASE}-ca"
    mkdir -p "$WORK/ca" && cp "$HOST_CA" "$WORK/ca/ca-certificates.crt"
    printf 'FROM %s\nCOPY ca-certificates.crt /etc/ssl/certs/ca-certificates.crt\nENV PIP_CERT=/etc/ssl/certs/ca-certificates.crt\n' \
        "$BASE" >"$WORK/ca/Dockerfile"
    docker build -q -t "${BASE}-ca" "$WORK/ca"
    BASE=${BASE}-ca
fi

FIND_LINKS=""
if [ -n "${WHEELS:-}" ]; then
    python3 -m http.server 8765 --bind 127.0.0.1 --directory "$WHEELS" >/dev/null 2>&1 &
    SERVER_PID=$!
    FIND_LINKS=http://127.0.0.1:8765/
fi

step "docker build pmvir:latest (base $BASE)"
docker build --network host -f docker/Dockerfile \
    --build-arg BASE_IMAGE="$BASE" --build-arg TORCH_INDEX="$TORCH_INDEX" --build-arg PIP_FIND_LINKS="$FIND_LINKS" \
    -t pmvir:latest .

step "docker build pmvir-redis:local"
printf 'FROM %s\nRUN apt-get update && apt-get install -y --no-install-recommends redis-server redis-tools && rm -rf /var/lib/apt/lists/*\n' \
    "$BASE" | docker build --network host -t pmvir-redis:local -

step "compose up: redis (AOF), api, 2 workers"
export PMVIR_API_KEYS=$KEY PMVIR_PORT=$PORT
"${COMPOSE[@]}" up -d --scale worker=2
for _ in $(seq 120); do
    curl -fsS "http://127.0.0.1:$PORT/readyz" >/dev/null 2>&1 && break
    sleep 1
done
curl -fsS "http://127.0.0.1:$PORT/readyz"; echo
"${COMPOSE[@]}" ps

step "a synthetic capture through the client"
$PMVIR synth --shape blob --out "$WORK/cap" --views 16 --size 256x216 --seed 3 --no-gt-views --quiet >/dev/null
rm -rf "$WORK/cap/gt"
$PMVIR submit "$WORK/cap" --server "http://127.0.0.1:$PORT" --api-key "$KEY" --stop-after geometry \
    --out "$WORK/result" --quiet
$PMVIR info --server "http://127.0.0.1:$PORT" --api-key "$KEY"
python3 - "$WORK/result" <<'PY'
import json, sys
from pathlib import Path
out = Path(sys.argv[1])
report = json.loads((out / "report.json").read_text())
assert report["stages"] == ["decode", "geometry"], report["stages"]
assert (out / "initial.ply").stat().st_size > 0 and any((out / "poses").iterdir())
print("result ok:", report["geometry"]["poses"]["registered_views"], "views registered,",
      report["geometry"]["subdivision"]["vertices"], "vertices;",
      "timings", {k: round(v, 1) for k, v in report["timings_s"].items()})
PY
"${COMPOSE[@]}" logs --no-color --tail 5 worker
step "done"
