#!/usr/bin/env bash
# Key files (./keys: operator.key, cloud.keys, edge-edge.keys, robot-robot{0,1,2}.keys) and a
# self-signed TLS certificate (./tls: cert.pem, key.pem for cloud, edge, localhost, 127.0.0.1)
# for docker-compose.secure.yml, made by the built image as the container user (so the files
# are readable in the containers and by no one else). Run from the repository, after
# `docker compose build`. Robots: ROBOTS="robot0 robot1 robot2" (default).
set -euo pipefail
cd "$(dirname "$0")/.."
robots=()
for r in ${ROBOTS:-robot0 robot1 robot2}; do robots+=(--robot "$r"); done
mkdir -p keys tls
docker run --rm --network none -e RECSLAM_WRITABLE="/keys /tls" \
    -v "$PWD/keys:/keys" -v "$PWD/tls:/tls" "${IMAGE:-recslam:latest}" sh -c \
    "recslam keys new --dir /keys --edge edge ${robots[*]} && \
     recslam keys tls --dir /tls --name cloud --name edge --name localhost --name 127.0.0.1"
