#!/usr/bin/env bash
# `make compose-test`: recslam's docker compose set-up, run for real from a fresh clone.
#
#  1. starts a Docker daemon if none answers, exactly as
#     `dockerd --iptables=false --ip-masq=false --bridge=none` (no firewall change; the
#     containers then use host networking: docker-compose.hostnet.yml);
#  2. makes the base image python:3.11-slim from Debian's packages (scripts/make-base-image.sh)
#     when it is not there and Docker Hub cannot be reached;
#  3. clones the committed HEAD into a temporary folder (a fresh clone: no datasets, no
#     ./out, no docker/secret.env) and follows docs/usage.md there: `make docker/secret.env`,
#     `docker compose build`, `docker compose --profile synth run --rm dataset` (a short set:
#     $ROBOTS robots x $SECONDS_PER_ROBOT s), `docker compose up -d`;
#  4. waits for the robots to exit, for the edge to drain, stops the stack (the cloud last,
#     timed) and checks the cloud's outputs (scripts/compose_check.py: trajectories, the ATE
#     report, every frame decoded exactly once at the edge, exit codes, no traceback);
#  5. checks loud failures on the built image: the placeholder secret, a non-empty folder the
#     container user cannot write, NETEM on a kernel without netem (and the restart policy
#     giving up on it), a robot whose edge is gone stopped with SIGTERM (bounded flush) and
#     giving up by itself after --give-up-after (exit 4, one line);
#  6. removes the stack (containers, volumes) and stops every daemon it started.
#
# Needs root (it may start dockerd), debootstrap when the base image must be made, docker
# compose (plugin) or docker-compose, and a few GB of disk. Environment: ROBOTS (3),
# SECONDS_PER_ROBOT (12), SECURE=1 adds docker-compose.secure.yml (a key file per service and
# TLS on both links, made by scripts/make-keys-and-tls.sh), KEEP=1 keeps the clone, CA_DIR (default
# /usr/local/share/ca-certificates: its *.crt go into the clone's docker/ca-certificates/, for
# builds behind a TLS-intercepting proxy). Exit code 0 when every check passed.
set -euo pipefail

ROBOTS="${ROBOTS:-3}"
SECONDS_PER_ROBOT="${SECONDS_PER_ROBOT:-12}"
CA_DIR="${CA_DIR:-/usr/local/share/ca-certificates}"
t0=$(date +%s)
repo="$(git -C "$(dirname "$0")/.." rev-parse --show-toplevel)"
work="$(mktemp -d /tmp/recslam-compose-test.XXXXXX)"
# shellcheck source=scripts/docker-lib.sh
. "$repo/scripts/docker-lib.sh" # start/stop the daemon, the base image, the clone, free_port
compose=()
files=(-f docker-compose.yml -f docker-compose.hostnet.yml)
if [ "${SECURE:-0}" = 1 ]; then files+=(-f docker-compose.secure.yml); fi
export COMPOSE_PROJECT_NAME=recslam-compose-test

say() { printf '[compose-test %4ss] %s\n' "$(($(date +%s) - t0))" "$*"; }
die() {
    say "FAIL: $*"
    exit 1
}

cleanup() {
    local rc=$?
    set +e
    if [ ${#compose[@]} -gt 0 ] && [ -d "$work/recslam" ] && [ -n "$(docker ps -aq \
        --filter "label=com.docker.compose.project=$COMPOSE_PROJECT_NAME" 2>/dev/null)" ]; then
        (cd "$work/recslam" && "${compose[@]}" "${files[@]}" --profile synth down -v \
            --remove-orphans >>"$work/down.log" 2>&1)
    fi
    stop_started_dockerd
    if [ "${KEEP:-0}" = "1" ] || [ $rc -ne 0 ]; then
        say "kept $work (logs: $work/*.log)"
    else
        rm -rf "$work"
    fi
    say "done in $(($(date +%s) - t0)) s, exit code $rc"
    exit $rc
}
trap cleanup EXIT

# 1. A Docker daemon.
start_dockerd_if_none
if docker compose version >/dev/null 2>&1; then
    compose=(docker compose)
elif command -v docker-compose >/dev/null; then
    compose=(docker-compose)
else
    die "neither 'docker compose' nor docker-compose found (Debian: apt-get install docker-compose)"
fi
say "compose: ${compose[*]} ($("${compose[@]}" version --short 2>/dev/null || echo '?')), engine $(docker version -f '{{.Server.Version}}')"

# 2. The base image.
ensure_base_image

# 3. A fresh clone, the commands of docs/usage.md ("Deployment and experiments").
fresh_clone
make -s docker/secret.env PYTHON=python3
CLOUD_PORT=$(free_port) EDGE_PORT=$(free_port) DASHBOARD_PORT=$(free_port)
export CLOUD_PORT EDGE_PORT DASHBOARD_PORT
say "ports: cloud $CLOUD_PORT, edge $EDGE_PORT, dashboard $DASHBOARD_PORT (host network)"
if [ "${compose[0]}" = docker-compose ]; then
    # docker-compose 1.x refuses published ports on the host network (Compose v2 ignores
    # them): run its resolved configuration without them.
    "${compose[@]}" "${files[@]}" --profile synth config >"$work/compose.resolved.yml"
    chmod 600 "$work/compose.resolved.yml" # it holds the secret
    say "docker-compose 1.x: $(python3 scripts/compose_check.py strip-ports "$work/compose.resolved.yml")"
    files=(-f "$work/compose.resolved.yml")
fi

tb=$(date +%s)
"${compose[@]}" "${files[@]}" build >"$work/build.log" 2>&1 || die "build failed: $(tail -5 "$work/build.log")"
size=$(docker image inspect -f '{{.Size}}' recslam:latest)
say "built recslam:latest in $(($(date +%s) - tb)) s: $((size / 1000000)) MB"
if [ "${SECURE:-0}" = 1 ]; then
    scripts/make-keys-and-tls.sh >"$work/keys.log" 2>&1 || die "keys: $(tail -5 "$work/keys.log")"
    say "key files and TLS certificate: $(ls keys | tr '\n' ' ')"
fi

td=$(date +%s)
"${compose[@]}" "${files[@]}" --profile synth run --rm dataset recslam -v dataset synth \
    --out /datasets/synth --robots "$ROBOTS" --seconds "$SECONDS_PER_ROBOT" --seed 0 \
    --no-progress >"$work/dataset.log" 2>&1 || die "dataset failed: $(tail -5 "$work/dataset.log")"
say "dataset ($ROBOTS robots x $SECONDS_PER_ROBOT s) in $(($(date +%s) - td)) s: $(grep -c '^  robot' "$work/dataset.log") sequences"
robots=()
for ((i = 0; i < ROBOTS; i++)); do robots+=("robot$i"); done
[ "$ROBOTS" = 3 ] || die "the compose file has three robots; ROBOTS=$ROBOTS needs another override"

tu=$(date +%s)
"${compose[@]}" "${files[@]}" up -d >"$work/up.log" 2>&1 || die "up failed: $(tail -5 "$work/up.log")"
say "stack up in $(($(date +%s) - tu)) s; waiting for the robots"
ids=()
for svc in robot1 robot2 robot3; do ids+=("$("${compose[@]}" "${files[@]}" ps -q "$svc")"); done
codes=$(timeout $((SECONDS_PER_ROBOT * 20 + 300)) docker wait "${ids[@]}" | tr '\n' ' ') ||
    die "robots not done after $((SECONDS_PER_ROBOT * 20 + 300)) s"
say "robots done $(($(date +%s) - tu)) s after up: exit codes $codes"
for _ in $(seq 240); do python3 scripts/compose_check.py drained out/compose && break; sleep 0.5; done
python3 scripts/compose_check.py drained out/compose || say "edge not drained after 120 s; stopping anyway"
sleep 3 # let the edge's last uplink reach the cloud
say "edge drained; stopping the stack"
"${compose[@]}" "${files[@]}" stop edge >>"$work/stop.log" 2>&1
ts=$(date +%s.%N)
"${compose[@]}" "${files[@]}" stop cloud >>"$work/stop.log" 2>&1
shutdown=$(python3 -c "print(f'{$(date +%s.%N) - $ts:.1f}')")
say "cloud stopped in $shutdown s after SIGTERM (stop_grace_period 120 s)"
"${compose[@]}" "${files[@]}" logs --no-color >"$work/compose.log" 2>&1
for svc in cloud edge robot1 robot2 robot3; do
    id=$("${compose[@]}" "${files[@]}" ps -q "$svc")
    state=$(docker inspect -f '{{.State.ExitCode}} restarts={{.RestartCount}}' "$id")
    say "  $svc: exit $state; last line: $(docker logs "$id" 2>&1 | tail -1 | cut -c1-150)"
done

# 4. The outputs.
failed=0
say "checking the cloud's outputs (out/compose)"
python3 scripts/compose_check.py outputs out/compose datasets/synth "${robots[@]}" || failed=1
for c in $codes; do [ "$c" = 0 ] || { say "FAIL: a robot exited with $c"; failed=1; }; done
for svc in cloud edge; do
    c=$(docker inspect -f '{{.State.ExitCode}}' "$("${compose[@]}" "${files[@]}" ps -q "$svc")")
    [ "$c" = 0 ] || { say "FAIL: $svc exited with $c"; failed=1; }
done
if grep -q Traceback "$work/compose.log"; then
    say "FAIL: a traceback in the services' logs:"
    grep -m1 -A12 Traceback "$work/compose.log"
    failed=1
fi

# 5. Loud failures, on the built image.
expect() { # expect CODE TEXT -- docker run args: the container exits CODE, its output has TEXT
    local want=$1 text=$2 got=0
    shift 3
    out=$(docker run --rm "$@" 2>&1) || got=$?
    if [ "$got" = "$want" ] && grep -qF -- "$text" <<<"$out"; then
        say "  ok   exit $got: $(grep -F -- "$text" <<<"$out" | head -1 | cut -c1-170)"
    else
        say "  FAIL exit $got (want $want, '$text'): $(tail -2 <<<"$out")"
        failed=1
    fi
}
say "loud failures"
expect 2 "placeholder secret" -- --network none -e RECSLAM_SECRET=change-me-to-a-long-random-string \
    recslam:latest recslam cloud --state-dir /state/cloud --dashboard-port 0
mkdir -p "$work/busy" && touch "$work/busy/file" && chmod 755 "$work/busy"
expect 78 "not writable by the container user" -- --network none -e RECSLAM_WRITABLE=/results \
    -v "$work/busy:/results" recslam:latest true
if grep -qsw sch_netem /proc/modules || [ -e /sys/module/sch_netem ]; then
    say "  (this kernel has netem: the no-netem message is not checked)"
else
    expect 78 "has no netem qdisc" -- --network none --cap-add NET_ADMIN -e NETEM="rate 100kbit" \
        -e NETEM_DEV=lo recslam:latest true
    # ... and the robots' restart policy gives up on it: on-failure:3, as in the compose file.
    policy=$(python3 -c 'import sys, yaml; print(yaml.safe_load(open(sys.argv[1]))["services"]["robot1"]["restart"])' \
        docker-compose.yml)
    id=$(docker run -d --network none --cap-add NET_ADMIN --restart "$policy" -e NETEM="rate 100kbit" \
        -e NETEM_DEV=lo recslam:latest true)
    for _ in $(seq 60); do [ "$(docker inspect -f '{{.State.Status}}' "$id")" = exited ] &&
        [ "$(docker inspect -f '{{.RestartCount}}' "$id")" -ge 3 ] && break; sleep 0.5; done
    sleep 2
    restarts=$(docker inspect -f '{{.State.Status}} after {{.RestartCount}} restarts, exit {{.State.ExitCode}}' "$id")
    docker rm -f "$id" >/dev/null
    if [ "$restarts" = "exited after 3 restarts, exit 78" ]; then
        say "  ok   restart: $policy with NETEM on this kernel: $restarts"
    else
        say "  FAIL restart: $policy with NETEM on this kernel: $restarts"
        failed=1
    fi
fi

# A robot whose edge is gone: the first SIGTERM flushes for a bounded time, logged.
port=$(free_port)
id=$(docker run -d --network host -e RECSLAM_SECRET="$(cut -d= -f2 docker/secret.env)" \
    -e SEQUENCE=synth/robot0 -e AGENT_ID=robot0 -e EDGE="127.0.0.1:$port" \
    -v "$PWD/datasets:/datasets:ro" recslam:latest recslam -v robot --stop-flush-timeout 3)
sleep 8
tstop=$(date +%s.%N)
docker stop -t 20 "$id" >/dev/null
took=$(python3 -c "print(f'{$(date +%s.%N) - $tstop:.1f}')")
code=$(docker inspect -f '{{.State.ExitCode}}' "$id")
robot_log=$(docker logs "$id" 2>&1)
docker rm "$id" >/dev/null
if [ "$code" = 130 ] && grep -q "stop requested" <<<"$robot_log" && grep -q "giving up with" <<<"$robot_log"; then
    say "  ok   robot without an edge stopped in $took s, exit $code: $(grep -o 'stop requested.*' <<<"$robot_log" | cut -c1-110)"
    say "       $(grep -o 'the edge did not take the backlog.*' <<<"$robot_log" | head -1 | cut -c1-140)"
else
    say "  FAIL robot without an edge: exit $code after $took s: $(tail -3 <<<"$robot_log")"
    failed=1
fi

# ... and with --give-up-after it exits by itself, non-zero, with one line saying why.
port=$(free_port)
expect 4 "giving up on 127.0.0.1:$port" -- --network host \
    -e RECSLAM_SECRET="$(cut -d= -f2 docker/secret.env)" -e SEQUENCE=synth/robot0 \
    -e AGENT_ID=robot0 -e EDGE="127.0.0.1:$port" -v "$PWD/datasets:/datasets:ro" \
    recslam:latest recslam robot --give-up-after 3

[ $failed = 0 ] || die "some checks failed (logs in $work)"
say "PASS: $ROBOTS robots x $SECONDS_PER_ROBOT s through docker compose; image $((size / 1000000)) MB; cloud shutdown $shutdown s"
