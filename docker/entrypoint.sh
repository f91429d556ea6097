#!/bin/sh
# Container entrypoint for every recslam service.
#
# Environment (all optional):
#   NETEM     tc-netem parameters for this container's uplink, e.g. "rate 100kbit delay 50ms
#             loss 1%"; applied to $NETEM_DEV (default eth0) as the root qdisc. Needs
#             cap_add: NET_ADMIN and a kernel with the sch_netem module. Empty: no shaping.
#             Refused with host networking (RECSLAM_HOST_NETWORK=1): it would shape the host.
#   RECSLAM_WRITABLE  space-separated folders the service writes (bind mounts such as the
#             cloud's /results, the dataset's /datasets): an empty folder owned by someone
#             else (Docker creates a missing bind-mount source as root) is handed to the user
#             recslam; a non-empty one it cannot write stops the container with one line.
#   SEQUENCE  a robot's sequence folder under /datasets (sets RECSLAM_DATASET=/datasets/$SEQUENCE)
#   AGENT_ID  a robot's id (sets RECSLAM_AGENT_ID)
#   EDGE      the edge's HOST:PORT for robots (sets RECSLAM_EDGE, default edge:7000)
#   RECSLAM_SECRET  the shared secret (from docker/secret.env), read by the services
# Then drops root (setpriv to user recslam) and runs the command, e.g. "recslam robot".
#
# Exit code 78 (EX_CONFIG) for a set-up error found here (NETEM, folders); the compose files
# restart a service on failure a few times only (restart: on-failure:N), so it does not loop.
set -eu


fail() {
    echo "recslam-entrypoint: $*" >&2
    exit 78
}

if [ -n "${NETEM:-}" ]; then
    dev="${NETEM_DEV:-eth0}"
    if [ "${RECSLAM_HOST_NETWORK:-0}" = "1" ]; then
        fail "NETEM='${NETEM}' refused: this container uses the host's network (it would shape the host's $dev)"
    fi
    # shellcheck disable=SC2086  # NETEM is a list of tc arguments
    if err="$(tc qdisc replace dev "$dev" root netem ${NETEM} 2>&1)"; then
        echo "netem on $dev: ${NETEM}"
    else
        case "$err" in
        *"qdisc kind is unknown"* | *"No such file or directory"*)
            fail "cannot apply NETEM='${NETEM}' on $dev: this kernel ($(uname -r)) has no netem qdisc (module sch_netem); shape with a kernel that has it, or with tbf / 'recslam experiment bandwidth' (tc said: ${err})" ;;
        *"Operation not permitted"*)
            fail "cannot apply NETEM='${NETEM}' on $dev: not permitted (the service needs cap_add: [NET_ADMIN]; tc said: ${err})" ;;
        *)
            fail "cannot apply NETEM='${NETEM}' on $dev: tc said: ${err}" ;;
        esac
    fi
fi

if [ "$(id -u)" = "0" ]; then
    for dir in ${RECSLAM_WRITABLE:-}; do
        mkdir -p "$dir"
        if setpriv --reuid=recslam --regid=recslam --init-groups test -w "$dir"; then
            continue
        fi
        if [ -z "$(ls -A "$dir")" ]; then
            chown recslam:recslam "$dir"
            echo "recslam-entrypoint: $dir was empty and not writable by recslam (uid $(id -u recslam)): now owned by it"
        else
            fail "$dir is not writable by the container user recslam (uid $(id -u recslam)) and not empty: on the host, chown -R $(id -u recslam):$(id -g recslam) the folder mounted there"
        fi
    done
fi

if [ -n "${SEQUENCE:-}" ]; then
    export RECSLAM_DATASET="/datasets/${SEQUENCE}"
fi
if [ -n "${AGENT_ID:-}" ]; then
    export RECSLAM_AGENT_ID="${AGENT_ID}"
fi
export RECSLAM_EDGE="${EDGE:-${RECSLAM_EDGE:-edge:7000}}"

if [ "$(id -u)" = "0" ]; then
    export HOME=/home/recslam USER=recslam
    exec setpriv --reuid=recslam --regid=recslam --init-groups "$@"
fi
exec "$@"
