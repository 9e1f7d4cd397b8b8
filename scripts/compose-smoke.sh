#!/usr/bin/env bash
# The container smoke test, step by step; a user can run it too (needs a Docker engine, Compose
# 1.29 `docker-compose` or v2 `docker compose`, and curl; CURLNAV_CLI: a host curlnav command).
#
#   build -> up with 3 actors -> /status shows 3 actors with episodes and learner version >= 1,
#   each its own bus identity (actor-<n>), no shared actor user -> stop one actor container, it
#   leaves /status; start it again, it claims a free identity -> restart the learner, its version goes on
#   above -> kill -9 replay, learner, scheduler (Docker SDK): nothing accepted lost -> pull the latest policy and run it -> bad configuration exits with one line
#   -> the bus refuses a service without credentials -> down -v -> the same services on a
#   single-node swarm (docker stack deploy of docker-stack.yml: the main node's router with TLS,
#   services on the node's network, bus credentials as Docker secrets, actors by task slot)
#   -> stack rm and its volumes -> clean up (the trap removes the stack's volumes too when a step fails).
#
#   bash scripts/compose-smoke.sh --images-only   # only the base image, the wheelhouse and the build
set -euo pipefail
cd "$(dirname "$0")/.."
export COMPOSE_PROJECT_NAME=${COMPOSE_PROJECT_NAME:-curlnavsmoke}
export BASE_IMAGE=${BASE_IMAGE:-curlnav-base:bookworm}
export CURLNAV_REPLAY__MIN_SIZE=300 CURLNAV_CHECKPOINT_EVERY_S=10 CURLNAV_EXPORT_EVERY_S=10
export CURLNAV_STATUS_PORT=${CURLNAV_STATUS_PORT:-18080} CURLNAV_LEARNER_PORT=${CURLNAV_LEARNER_PORT:-18081}
CLI=${CURLNAV_CLI:-.venv/bin/curlnav}
PY=${CURLNAV_PY:-.venv/bin/python}
STATUS=http://127.0.0.1:$CURLNAV_STATUS_PORT/status
LEARNER=http://127.0.0.1:$CURLNAV_LEARNER_PORT
if docker compose version >/dev/null 2>&1; then DC=(docker compose); else DC=(docker-compose); fi
start=$(date +%s)
step() { printf '\n[smoke %4ss] %s\n' "$(( $(date +%s) - start ))" "$*"; }
# wait_for DESCRIPTION SECONDS PYTHON-EXPRESSION-ON-status [ARG...] (sys.argv[3:] in the expression)
wait_for() {
  local what=$1 limit=$2 expr=$3 deadline=$(( $(date +%s) + $2 ))
  while true; do
    if "$PY" - "$STATUS" "$expr" "${@:4}" <<'EOF' 2>/dev/null; then return 0; fi
import json, sys, urllib.request
status = json.load(urllib.request.urlopen(sys.argv[1], timeout=3))
actors = status["live_actors"]
sys.exit(0 if eval(sys.argv[2]) else 1)
EOF
    if [ "$(date +%s)" -ge "$deadline" ]; then
      echo "TIMEOUT after ${limit}s waiting for: $what"; curl -s "$STATUS" | head -c 3000 || true
      "${DC[@]}" ps || true; "${DC[@]}" logs --tail 30 || true
      return 1
    fi
    sleep 2
  done
}
# remove_stack: docker stack rm, wait for its containers, then remove its volumes (which stack rm keeps)
source scripts/stack-cleanup.sh
cleanup() {
  "${DC[@]}" down -v --remove-orphans >/dev/null 2>&1 || true
  remove_stack curlnav || true  # also on failure: a later swarm run must not pick up this one's state
  docker swarm leave --force >/dev/null 2>&1 || true
  [ -z "${bus_tmp:-}" ] || rm -rf "$bus_tmp"
}
images_only=false; [ "${1:-}" != --images-only ] || images_only=true
if ! $images_only; then
  trap cleanup EXIT
  cleanup  # leftovers of an interrupted run (a compose project, a stack, a swarm)
fi

step "base image $BASE_IMAGE and wheelhouse"
[ "$BASE_IMAGE" = curlnav-base:bookworm ] && bash scripts/make-base-image.sh "$BASE_IMAGE"
ls wheelhouse/*.whl >/dev/null 2>&1 || bash scripts/make-wheelhouse.sh

step "build (${DC[*]} build)"
"${DC[@]}" build --build-arg BASE_IMAGE="$BASE_IMAGE" router
docker image ls curlnav:latest
if $images_only; then step "images made"; exit 0; fi

step "up with 3 actors"
"${DC[@]}" up -d --scale actor=3
wait_for "3 live actors, each with episodes, learner version >= 1" 420 \
  'len(actors) == 3 and all(a.get("episodes", 0) > 0 for a in actors.values()) and (status["learner"]["version"] or 0) >= 1'
curl -s "$STATUS" | "$PY" -c 'import json,sys; s=json.load(sys.stdin); print("status:", {k: s[k] for k in ("stage", "episodes", "learner", "replay")}, "actors:", sorted(s["live_actors"]))'

step "one bus identity per replica: 3 distinct actor-<n>, each a user of the router; no shared actor user"
users=$("${DC[@]}" exec -T router cut -d: -f1 /bus/users.txt)
echo "router's users:" $users
if echo "$users" | grep -qx actor; then echo "the shared actor user is still there"; exit 1; fi
wait_for "the live actors are 3 distinct identities the router knows" 30 \
  "len(actors) == 3 and all(a in sys.argv[3].split() and a.startswith('actor-') for a in actors)" "$users"
"${DC[@]}" logs actor | grep -o "claimed bus identity actor-[0-9]*" | sort | uniq -c

step "stop one actor container; it leaves /status; started again, it claims a free identity"
victim=$("${DC[@]}" ps -q actor | sed -n 1p)  # sed reads all: no SIGPIPE under pipefail
docker stop "$victim" >/dev/null
wait_for "2 live actors" 60 'len(actors) == 2'
docker start "$victim" >/dev/null
wait_for "3 live actors again, distinct identities" 180 'len(actors) == 3 and all(a.startswith("actor-") for a in actors)'

step "restart the learner; training resumes from its checkpoint"
before=$(curl -s "$LEARNER/healthz" | "$PY" -c 'import json,sys; print(json.load(sys.stdin)["version"])')
"${DC[@]}" restart learner
# Poll the restarted learner's own /healthz (the scheduler's /status may still show the version it
# heard before the restart, and the learner's HTTP port answers only once it has loaded).
after=""
deadline=$(( $(date +%s) + 180 ))
while [ "$(date +%s)" -lt "$deadline" ]; do
  after=$(curl -s --max-time 3 "$LEARNER/healthz" 2>/dev/null | "$PY" -c 'import json,sys; print(json.load(sys.stdin)["version"])' 2>/dev/null) || after=""
  if [ -n "$after" ] && [ "$after" -ge "$before" ]; then break; fi
  sleep 2
done
if [ -z "$after" ]; then echo "TIMEOUT after 180s: the restarted learner's /healthz never answered"; "${DC[@]}" logs --tail 30 learner || true; exit 1; fi
echo "learner version before restart $before, after $after"
[ "$after" -gt "$before" ]  # a restarted learner numbers its weights above every version published

step "fault injection (Docker SDK): kill -9 replay, learner, scheduler in turn; nothing accepted lost"
"$PY" scripts/compose_faults.py --project "$COMPOSE_PROJECT_NAME" --status "$STATUS" --pause-s 3

step "pull the latest policy (curlnav pull, and the same with curl) and run it"
curl -sf "$LEARNER/policy/latest" | "$PY" -c 'import json,sys; d=json.load(sys.stdin); print("policy", d["version"], {k: v.get("sha256", "")[:12] for k, v in d["files"].items()})'
rm -rf /tmp/curlnav-smoke-policy
"$CLI" pull --from "$LEARNER" --out /tmp/curlnav-smoke-policy
"$CLI" policy run /tmp/curlnav-smoke-policy --world open-room --pair across --out /tmp/curlnav-smoke-pics

step "bad configuration: one line in the logs, no hang"
set +e
docker run --rm --network "${COMPOSE_PROJECT_NAME}_default" -e CURLNAV_ROUTER=tcp/router:7447 curlnav:latest actor --world atlantis 2>&1 | tail -n 2
docker run --rm curlnav:latest scheduler --curriculum /nonexistent.yaml 2>&1 | tail -n 1
timeout 60 docker run --rm -e CURLNAV_ROUTER_TIMEOUT_S=5 curlnav:latest replay --router tcp/127.0.0.1:7447 2>&1 | tail -n 1
set -e

step "the bus refuses a service without the run's credentials"
set +e
refused=$(timeout 90 docker run --rm --network "${COMPOSE_PROJECT_NAME}_default" -e CURLNAV_ROUTER=tcp/router:7447 \
  -e CURLNAV_ROUTER_TIMEOUT_S=5 curlnav:latest replay 2>&1 | tail -n 1)
set -e
echo "$refused"
echo "$refused" | grep -q "cannot reach the Zenoh router at tcp/router:7447"

step "down -v"
"${DC[@]}" down -v --remove-orphans

step "the same services on a single-node swarm (docker stack deploy -c docker-stack.yml)"
docker swarm init --advertise-addr 127.0.0.1 >/dev/null
docker node update --label-add curlnav=main "$(docker node ls -q)" >/dev/null  # the main node
bus_tmp=$(mktemp -d)
export CURLNAV_BUS=$bus_tmp/bus CURLNAV_MAIN_ADDRESS=127.0.0.1  # the stack's secrets are read from CURLNAV_BUS
# the header's command: 16 actor identities, the run's CA and the main and node routers' certificates
"$CLI" bus credentials --run compose --out "$CURLNAV_BUS" --actors 16 --tls main=127.0.0.1,node | sed -n 1p
CURLNAV_CURRICULA=$PWD/scheduler/curricula docker stack deploy -c docker-stack.yml curlnav
wait_for "swarm: 2 live actors with episodes (actor-0 and actor-1: task slots 1 and 2), learner version >= 1" 420 \
  'sorted(actors) == ["actor-0", "actor-1"] and all(a.get("episodes", 0) > 0 for a in actors.values()) and (status["learner"]["version"] or 0) >= 1'
# grep -c reads the logs whole (grep -m1 would close the pipe early: `docker service logs` then dies of
# SIGPIPE and, under pipefail, the check failed with the line found); polled, as swarm hands logs over late
tls_deadline=$((SECONDS + 60))
until [ "$(docker service logs curlnav_router 2>&1 | grep -c "mutual TLS" || true)" -gt 0 ]; do
  if [ "$SECONDS" -ge "$tls_deadline" ]; then echo "the main router did not start with TLS"; exit 1; fi
  sleep 2
done
echo "the main router started with mutual TLS"
step "docker stack rm, then its volumes (stack rm keeps them)"
remove_stack curlnav
left=$(docker volume ls -q | grep -E '^curlnav_(learner|replay|scheduler)$' || true)
if [ -n "$left" ]; then echo "volumes left behind: $left"; exit 1; fi
docker swarm leave --force >/dev/null

step "smoke test passed"
