# Shared steps of `make compose-test` and `make swarm-test` (sourced, not run). The caller
# defines say and die, and sets work (its temporary folder), repo (the repository) and
# CA_DIR; started_dockerd is set here when a daemon is started.

started_dockerd=""

# A Docker daemon: the one that answers, else `dockerd --iptables=false --ip-masq=false
# --bridge=none` started here (no firewall change), its pid in started_dockerd.
start_dockerd_if_none() {
    if docker info >/dev/null 2>&1; then
        say "using the running Docker daemon"
        return
    fi
    [ "$(id -u)" = 0 ] || die "no Docker daemon answers and this is not root: cannot start one"
    command -v dockerd >/dev/null || die "dockerd not found (Debian: apt-get install docker.io)"
    say "starting dockerd --iptables=false --ip-masq=false --bridge=none (log $work/dockerd.log)"
    setsid dockerd --iptables=false --ip-masq=false --bridge=none >"$work/dockerd.log" 2>&1 &
    started_dockerd=$!
    for _ in $(seq 60); do docker info >/dev/null 2>&1 && break; sleep 0.5; done
    docker info >/dev/null 2>&1 || die "dockerd did not answer within 30 s: $(tail -3 "$work/dockerd.log")"
}

# Stop the daemon start_dockerd_if_none started (SIGTERM, up to 30 s), if any.
stop_started_dockerd() {
    [ -n "$started_dockerd" ] || return 0
    say "stopping the Docker daemon this test started (pid $started_dockerd)"
    kill -TERM "$started_dockerd" 2>/dev/null
    for _ in $(seq 60); do kill -0 "$started_dockerd" 2>/dev/null || break; sleep 0.5; done
    kill -0 "$started_dockerd" 2>/dev/null && say "dockerd $started_dockerd still running after 30 s"
    return 0
}

# The base image python:3.11-slim: present, pulled, or made from Debian's packages.
ensure_base_image() {
    if docker image inspect python:3.11-slim >/dev/null 2>&1; then
        say "base image python:3.11-slim present"
    elif timeout 60 docker pull python:3.11-slim >"$work/pull.log" 2>&1; then
        say "pulled python:3.11-slim"
    else
        say "Docker Hub unreachable ($(tail -1 "$work/pull.log")): making python:3.11-slim from Debian packages"
        "$repo/scripts/make-base-image.sh" python:3.11-slim
    fi
}

# A fresh clone of the committed HEAD in $work/recslam, made the current folder, with the
# host's CA certificates ($CA_DIR/*.crt) for builds behind a TLS-intercepting proxy.
fresh_clone() {
    git clone -q "$repo" "$work/recslam"
    cd "$work/recslam"
    say "fresh clone of $(git rev-parse --short HEAD) in $work/recslam"
    if ls "$CA_DIR"/*.crt >/dev/null 2>&1; then
        cp "$CA_DIR"/*.crt docker/ca-certificates/
        say "CA certificates for the build: $(cd "$CA_DIR" && echo *.crt)"
    fi
}

free_port() { python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])'; }
