#!/bin/sh
# Container entrypoint for every recslam service.
#
# Environment (all optional):
#   NETEM     tc-netem parameters for this container's uplink, e.g. "rate 100kbit delay 50ms
#             loss 1%"; applied to $NETEM_DEV (default eth0) as the root qdisc. Needs
#             cap_add: NET_ADMIN. Empty: no shaping.
#   SEQUENCE  a robot's sequence folder under /datasets (sets RECSLAM_DATASET=/datasets/$SEQUENCE)
#   AGENT_ID  a robot's id (sets RECSLAM_AGENT_ID)
#   EDGE      the edge's HOST:PORT for robots (sets RECSLAM_EDGE, default edge:7000)
#   RECSLAM_SECRET  the shared secret (from docker/secret.env), read by the services
# Then drops root (setpriv to user recslam) and runs the command, e.g. "recslam robot".
set -eu

if [ -n "${NETEM:-}" ]; then
    dev="${NETEM_DEV:-eth0}"
    # shellcheck disable=SC2086  # NETEM is a list of tc arguments
    if tc qdisc replace dev "$dev" root netem ${NETEM}; then
        echo "netem on $dev: ${NETEM}"
    else
        echo "cannot apply NETEM='${NETEM}' on $dev (cap_add: NET_ADMIN?)" >&2
        exit 3
    fi
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
