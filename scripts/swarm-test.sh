#!/usr/bin/env bash
# `make swarm-test`: recslam's Docker Swarm stack (docker-compose.swarm.yml) deployed for real
# on a one-node swarm here, with the edge's and a robot's task killed under the engine.
#
#  1. daemon: starts `dockerd --iptables=false --ip-masq=false --bridge=none` if none answers
#     (no firewall change; overlay networks cannot run then, so the stack runs with
#     RECSLAM_SWARM_NETWORK=host: every service on the node's own network, on 127.0.0.1);
#  2. base image: python:3.11-slim made from Debian's packages (scripts/make-base-image.sh)
#     when it is missing and Docker Hub cannot be reached, as `make compose-test` does;
#  3. clone: the committed HEAD cloned into a temporary folder (no keys, no datasets);
#  4. build: `docker build` of the image (recslam:latest; the host's CA certificates added);
#  5. dataset: the short synthetic set of `make compose-test` ($ROBOTS robots x
#     $SECONDS_PER_ROBOT s, seed 0), made by the image;
#  6. swarm: `docker swarm init --advertise-addr 127.0.0.1` unless the node is in a swarm
#     already, and the node labels of the stack file (cloud, site a, robot0..robot2);
#  7. keys: `recslam keys new` in the image (scripts/make-keys-and-tls.sh): `docker stack
#     deploy` turns each service's key file into its own swarm secret;
#  8. per phase (clean, then each of $FAULTS: "edge", "robot"): `docker stack deploy` on fresh
#     volumes; waits for the robots to finish (in "edge": `docker kill` of the edge's container
#     once the edge decoded $KILL_AT frames of robot0, in "robot": of robot2's container (agent
#     robot1) once the edge decoded $KILL_AT of its frames; swarm's restart policy brings
#     either back), waits for the edge to drain, scales the edge and then the cloud to 0
#     (SIGTERM, the cloud's shutdown timed), and checks the cloud's outputs with the checker of
#     `make compose-test` (scripts/compose_check.py: a trajectory per robot, one map, every
#     frame decoded exactly once at the edge, joint ATE <= $MAX_JOINT_ATE m), the tasks' exit
#     codes (`docker events`: the killed one 137 and restarted, every other 0), the restart
#     (the edge: "replaying N journaled messages" from its volume; the robot, which keeps no
#     journal, plays its sequence again from frame 0: the edge starts a new VIO map for that
#     stream, which the cloud merges) and no traceback in any log; then `docker stack rm` and
#     the stack's volumes removed;
#  9. a table of the phases; leaves the swarm it created and stops the daemon it started (also
#     on failure: trap). Images stay, so a second run reuses them.
#
# Every step is named; a failing step says which one and the exit code is non-zero. Needs
# root (it may start dockerd), debootstrap when the base image must be made, and a few GB of
# disk. Environment: SECONDS_PER_ROBOT (12), FAULTS ("edge robot"; "" runs the clean phase
# only), KILL_AT (80 frames), MAX_JOINT_ATE (0.03 m), KEEP=1 keeps the work folder, CA_DIR
# (default /usr/local/share/ca-certificates). Exit code 0 when every check passed.
set -euo pipefail

ROBOTS=3 # the stack file has three robots
SECONDS_PER_ROBOT="${SECONDS_PER_ROBOT:-12}"
FAULTS="${FAULTS-edge robot}"
KILL_AT="${KILL_AT:-80}"
MAX_JOINT_ATE="${MAX_JOINT_ATE:-0.03}"
CA_DIR="${CA_DIR:-/usr/local/share/ca-certificates}"
STACK=recslam-swarm-test
IMAGE=recslam:latest
t0=$(date +%s)
repo="$(git -C "$(dirname "$0")/.." rev-parse --show-toplevel)"
work="$(mktemp -d /tmp/recslam-swarm-test.XXXXXX)"
# shellcheck source=scripts/docker-lib.sh
. "$repo/scripts/docker-lib.sh" # start/stop the daemon, the base image, the clone, free_port
started_swarm=""
deployed=""
watchers=() # the `docker events` and `docker service logs --follow` of the current phase
step="start"
summary=()

say() { printf '[swarm-test %4ss] %s\n' "$(($(date +%s) - t0))" "$*"; }
die() {
    say "FAIL in step '$step': $*"
    exit 1
}
begin() {
    step="$1"
    say "-- $step"
}

# Stop the phase's event and log watchers (processes this script started).
stop_watchers() {
    local pid
    for pid in "${watchers[@]}"; do kill "$pid" 2>/dev/null || true; done
    for pid in "${watchers[@]}"; do wait "$pid" 2>/dev/null || true; done
    watchers=()
}

# The stack's containers and volumes gone (stack rm is asynchronous).
remove_stack() {
    docker stack rm "$STACK" >>"$work/rm.log" 2>&1 || true
    for _ in $(seq 120); do
        [ -z "$(docker ps -aq --filter "label=com.docker.stack.namespace=$STACK")" ] && break
        sleep 0.5
    done
    local vols
    vols=$(docker volume ls -q --filter "label=com.docker.stack.namespace=$STACK")
    if [ -n "$vols" ]; then
        # shellcheck disable=SC2086  # one volume name per word
        docker volume rm $vols >>"$work/rm.log" 2>&1 || say "volumes not removed: $vols"
    fi
    deployed=""
}

cleanup() {
    local rc=$?
    set +e
    stop_watchers
    if [ -n "$deployed" ]; then
        say "removing the stack $STACK"
        remove_stack
    fi
    if [ -n "$started_swarm" ]; then
        say "leaving the swarm this test created"
        docker swarm leave --force >>"$work/swarm.log" 2>&1 || say "swarm leave failed: $(tail -1 "$work/swarm.log")"
    fi
    stop_started_dockerd
    if [ "${KEEP:-0}" = "1" ] || [ $rc -ne 0 ]; then
        say "kept $work (logs: $work/*.log, $work/*/)"
    else
        rm -rf "$work"
    fi
    [ $rc -eq 0 ] || say "FAILED in step '$step'"
    say "done in $(($(date +%s) - t0)) s, exit code $rc"
    exit $rc
}
trap cleanup EXIT

# The edge's count of frames decoded for AGENT (0 before its stats exist).
decoded() {
    python3 - "$1" "$2" <<'EOF'
import json, sys
try:
    robots = json.load(open(sys.argv[1])).get("robots", {})
except (OSError, ValueError):
    robots = {}
print(robots.get(sys.argv[2], {}).get("frames_decoded", 0))
EOF
}

# The tasks of service NAME (of the stack), oldest first: "ID STATE EXIT" per line.
tasks() {
    local id
    for id in $(docker service ps -q --no-trunc "${STACK}_$1"); do
        docker inspect -f '{{.ID}} {{.CreatedAt.UnixNano}} {{.Status.State}} {{with .Status.ContainerStatus}}{{.ExitCode}}{{else}}-{{end}}' "$id"
    done | sort -k2,2n | awk '{print $1, $3, $4}'
}

# The running container of service NAME.
container_of() { docker ps -q --filter "label=com.docker.swarm.service.name=${STACK}_$1" | head -1; }

# Scale service NAME to 0 (SIGTERM, then SIGKILL after its stop_grace_period) and wait until
# its container has exited (the CLI's convergence can come first); prints the seconds taken,
# or says why not on stderr and returns 1.
stop_service() {
    local ts
    ts=$(date +%s.%N)
    if ! docker service scale --detach=true "${STACK}_$1=0" >>"$2/stop.log" 2>&1; then
        echo "scaling $1 to 0 failed: $(tail -3 "$2/stop.log")" >&2
        return 1
    fi
    for _ in $(seq 300); do [ -z "$(container_of "$1")" ] && break; sleep 0.5; done
    if [ -n "$(container_of "$1")" ]; then
        echo "$1 still running 150 s after it was scaled to 0" >&2
        return 1
    fi
    python3 -c "print(f'{$(date +%s.%N) - $ts:.1f}')"
}

# -------------------------------------------------------------------------------------------
begin "daemon"
start_dockerd_if_none
say "engine $(docker version -f '{{.Server.Version}}'), CLI $(docker version -f '{{.Client.Version}}')"

begin "base image"
ensure_base_image

begin "clone"
fresh_clone

begin "build"
tb=$(date +%s)
# The legacy builder where the CLI has no buildx (Debian's docker.io), as compose-test's
# docker-compose 1.29 uses it; the build reaches pip through the host's network.
docker buildx version >/dev/null 2>&1 || export DOCKER_BUILDKIT=0
docker build --network host -t "$IMAGE" . >"$work/build.log" 2>&1 || die "build failed: $(tail -5 "$work/build.log")"
size=$(docker image inspect -f '{{.Size}}' "$IMAGE")
say "built $IMAGE in $(($(date +%s) - tb)) s: $((size / 1000000)) MB"

begin "dataset"
td=$(date +%s)
mkdir -p datasets
docker run --rm --network host -e RECSLAM_WRITABLE=/datasets -v "$PWD/datasets:/datasets" "$IMAGE" \
    recslam -v dataset synth --out /datasets/synth --robots "$ROBOTS" --seconds "$SECONDS_PER_ROBOT" \
    --seed 0 --no-progress >"$work/dataset.log" 2>&1 || die "dataset failed: $(tail -5 "$work/dataset.log")"
say "dataset ($ROBOTS robots x $SECONDS_PER_ROBOT s) in $(($(date +%s) - td)) s: $(grep -c '^  robot' "$work/dataset.log") sequences"

begin "swarm"
state=$(docker info -f '{{.Swarm.LocalNodeState}}')
if [ "$state" = inactive ]; then
    docker swarm init --advertise-addr 127.0.0.1 >"$work/swarm.log" 2>&1 || die "swarm init: $(tail -3 "$work/swarm.log")"
    started_swarm=1
    say "docker swarm init --advertise-addr 127.0.0.1: $(head -1 "$work/swarm.log")"
else
    say "this node is in a swarm already ($state): using it, not leaving it"
fi
node=$(docker info -f '{{.Swarm.NodeID}}')
# The stack file's placement: the cloud, the edge of site a and every robot on this one node.
docker node update --label-add recslam.role=cloud --label-add recslam.site=a \
    --label-add recslam.robot.robot0=true --label-add recslam.robot.robot1=true \
    --label-add recslam.robot.robot2=true "$node" >/dev/null
say "node $node labels: $(docker node inspect -f '{{json .Spec.Labels}}' "$node")"

begin "keys"
scripts/make-keys-and-tls.sh >"$work/keys.log" 2>&1 || die "keys: $(tail -5 "$work/keys.log")"
say "key files: $(cd keys && echo *.keys) (keys/operator.key stays here)"

# -------------------------------------------------------------------------------------------
# One deployment of the stack; FAULT is "" (clean), "edge" or "robot".
run_phase() {
    local fault=$1 phase=${1:-clean} victim="" agent="" killed="" restarted=""
    local out="$work/$phase" cloud_port edge_port dash_port tu edge_stats
    mkdir -p "$out"
    case "$fault" in
    edge) victim=edge agent=robot0 ;;
    robot) victim=robot2 agent=robot1 ;;
    "") ;;
    *) die "unknown fault '$fault' (FAULTS: edge, robot)" ;;
    esac

    begin "deploy ($phase)"
    # Every container's exit, as the engine reports it: swarm removes a task scaled down to 0
    # (and its container), so its exit code is only seen here.
    docker events --filter type=container --filter event=die \
        --filter "label=com.docker.stack.namespace=$STACK" --format \
        '{{index .Actor.Attributes "com.docker.swarm.service.name"}} {{index .Actor.Attributes "exitCode"}}' \
        >"$out/exits.log" 2>&1 &
    watchers+=($!)
    cloud_port=$(free_port) edge_port=$(free_port) dash_port=$(free_port)
    tu=$(date +%s)
    RECSLAM_SWARM_NETWORK=host LISTEN_HOST=127.0.0.1 CLOUD_HOST=127.0.0.1 EDGE_HOST=127.0.0.1 \
        CLOUD_PORT=$cloud_port EDGE_PORT=$edge_port DASHBOARD_PORT=$dash_port \
        RECSLAM_IMAGE=$IMAGE RECSLAM_DATASETS="$PWD/datasets" GROUNDTRUTH=synth \
        docker stack deploy --resolve-image never -c docker-compose.swarm.yml "$STACK" \
        >"$out/deploy.log" 2>&1 || die "stack deploy: $(tail -5 "$out/deploy.log")"
    deployed=1
    local svc
    for svc in cloud edge robot1 robot2 robot3; do # every task's log, the restarted ones too
        docker service logs --follow --raw "${STACK}_$svc" >"$out/$svc.log" 2>&1 &
        watchers+=($!)
    done
    say "deployed (host network; cloud :$cloud_port, edge :$edge_port, dashboard :$dash_port): $(docker stack services "$STACK" --format '{{.Name}}' | sort | tr '\n' ' ')"
    say "secrets: $(docker secret ls --filter "label=com.docker.stack.namespace=$STACK" --format '{{.Name}}' | sort | tr '\n' ' ')"

    begin "robots ($phase)"
    for _ in $(seq 120); do
        edge_stats="$(docker volume inspect -f '{{.Mountpoint}}' "${STACK}_edge-results" 2>/dev/null)/edge-stats.json" && break
        sleep 0.5
    done
    local deadline=$((SECONDS_PER_ROBOT * 20 + 300)) done_robots
    while :; do
        if [ -n "$victim" ] && [ -z "$killed" ] && [ "$(decoded "$edge_stats" "$agent")" -ge "$KILL_AT" ]; then
            local id
            id=$(container_of "$victim")
            [ -n "$id" ] || die "no running container of $victim to kill"
            docker kill "$id" >/dev/null || die "docker kill of $victim's container ${id:0:12} failed"
            killed=$(($(date +%s) - tu))
            say "killed $victim's container ${id:0:12} (SIGKILL) $killed s after deploy, the edge having decoded $(decoded "$edge_stats" "$agent") frames of $agent"
        fi
        if [ -n "$killed" ] && [ -z "$restarted" ] && [ "$(tasks "$victim" | grep -c ' running ')" = 1 ] &&
            [ "$(tasks "$victim" | wc -l)" -ge 2 ]; then
            restarted=$(($(date +%s) - tu))
            say "swarm restarted $victim: a new task running $((restarted - killed)) s after the kill"
        fi
        done_robots=0
        for svc in robot1 robot2 robot3; do
            if tasks "$svc" | tail -1 | grep -q ' complete '; then done_robots=$((done_robots + 1)); fi
        done
        [ "$done_robots" = 3 ] && break
        [ $(($(date +%s) - tu)) -lt $deadline ] || die "robots not done $deadline s after deploy: $(for s in robot1 robot2 robot3; do echo "$s: $(tasks "$s" | tr '\n' ';')"; done)"
        sleep 1
    done
    say "robots done $(($(date +%s) - tu)) s after deploy"
    if [ -n "$victim" ]; then
        [ -n "$killed" ] || die "the robots finished before the edge decoded $KILL_AT frames of $agent: nothing killed"
        [ -n "$restarted" ] || die "$victim was killed but swarm did not restart it"
    fi

    begin "drain ($phase)"
    for _ in $(seq 240); do python3 scripts/compose_check.py drained "$(dirname "$edge_stats")" && break; sleep 0.5; done
    python3 scripts/compose_check.py drained "$(dirname "$edge_stats")" || say "edge not drained after 120 s; stopping anyway"
    sleep 3 # let the edge's last uplink reach the cloud
    local edge_stop shutdown
    edge_stop=$(stop_service edge "$out") || die "the edge did not stop"
    shutdown=$(stop_service cloud "$out") || die "the cloud did not stop"
    say "edge drained and stopped in $edge_stop s; cloud stopped in $shutdown s after SIGTERM (stop_grace_period 120 s)"
    sleep 2 # the last log lines and events
    stop_watchers

    begin "check ($phase)"
    local failed=0 exits want
    for svc in cloud edge robot1 robot2 robot3; do
        exits=$(awk -v s="${STACK}_$svc" '$1 == s {printf "%s%s", sep, $2; sep=" "}' "$out/exits.log")
        want=0
        [ "$svc" = "$victim" ] && want="137 0"
        if [ "$exits" = "$want" ]; then
            say "  ok   $svc: container exit codes: $exits"
        else
            say "  FAIL $svc: container exit codes: '$exits' (want '$want')"
            failed=1
        fi
    done
    if [ "$victim" = edge ]; then
        if grep -q "replaying [0-9]* journaled messages" "$out/edge.log"; then
            say "  ok   the restarted edge resumed from its journal: $(grep -o 'robot [a-z0-9]*: replaying [0-9]* journaled messages' "$out/edge.log" | tr '\n' ';')"
        else
            say "  FAIL the restarted edge did not replay a journal"
            failed=1
        fi
    fi
    if [ "$victim" = robot2 ]; then # it plays its sequence again from frame 0: a new stream
        if grep -q "robot $agent restarted its stream: a new VIO" "$out/edge.log"; then
            say "  ok   the edge took $agent's new stream: $(grep -o "robot $agent restarted its stream: a new VIO.*" "$out/edge.log" | head -1)"
        else
            say "  FAIL the edge did not start a new VIO map for $agent's new stream"
            failed=1
        fi
    fi
    if grep -l Traceback "$out"/*.log >/dev/null 2>&1; then
        say "  FAIL a traceback in the services' logs: $(grep -l Traceback "$out"/*.log | tr '\n' ' ')"
        failed=1
    fi
    mkdir -p "$out/results"
    cp -a "$(docker volume inspect -f '{{.Mountpoint}}' "${STACK}_cloud-results")/." "$out/results/"
    cp "$edge_stats" "$out/results/edge-stats.json"
    python3 scripts/compose_check.py outputs "$out/results" datasets/synth robot0 robot1 robot2 \
        --max-joint-ate "$MAX_JOINT_ATE" | tee "$out/check.txt" || failed=1
    local joint frames maps
    joint=$(grep -o 'joint ATE RMSE [0-9.]* m (one map)' "$out/check.txt" | awk '{print $4}' || true)
    frames=$(grep -o 'robot[0-9]: [0-9]* of [0-9]* frames' "$out/check.txt" |
        awk '{printf "%s%s/%s", sep, $2, $4; sep=" "}' || true)
    maps=$(grep -o 'maps \[[^]]*\]' "$out/check.txt" | head -1 | cut -c6- || true)
    summary+=("$(printf '%-6s joint ATE %s m, frames decoded %s, maps %s, killed %s, cloud shutdown %s s' \
        "$phase" "${joint:-none}" "$frames" "$maps" "${victim:-none}" "$shutdown")")

    begin "remove ($phase)"
    remove_stack
    say "stack removed with its volumes"
    step="check ($phase)"
    [ $failed = 0 ] || die "checks failed (logs and outputs in $out)"
}

for fault in "" $FAULTS; do run_phase "$fault"; done

begin "summary"
for s in "${summary[@]}"; do say "  $s"; done
say "PASS: the swarm stack ran $((${#summary[@]})) time(s) on a one-node swarm (host network); image $((size / 1000000)) MB"
