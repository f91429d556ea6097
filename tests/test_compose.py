"""Static checks of docker-compose.yml, the EuRoC override, the Dockerfile and the entrypoint
(no Docker engine runs on the test machines)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml

from recslam.cli import build_parser

ROOT = Path(__file__).resolve().parents[1]
COMPOSE = ROOT / "docker-compose.yml"
EUROC = ROOT / "docker-compose.euroc.yml"
ENTRYPOINT = ROOT / "docker" / "entrypoint.sh"
VAR = re.compile(r"\$\{(\w+)(?::-([^}]*))?\}")
# What the entrypoint exports for a robot (see docker/entrypoint.sh).
ROBOT_ENV = {"RECSLAM_DATASET": "/datasets/x", "RECSLAM_AGENT_ID": "r", "RECSLAM_EDGE": "edge:7000"}


def _substitute(text: str) -> str:
    """Compose variable substitution with every variable unset (defaults apply)."""
    return VAR.sub(lambda m: m.group(2) or "", text)


def _load(path: Path) -> dict:
    return yaml.safe_load(path.read_text())


def _merged() -> dict[str, dict]:
    """Services of docker-compose.yml with docker-compose.euroc.yml applied on top."""
    services = {k: dict(v) for k, v in _load(COMPOSE)["services"].items()}
    for name, over in _load(EUROC)["services"].items():
        services[name] = {**services.get(name, {}), **over}
    return services


def _flag(command: list[str], flag: str) -> str:
    return command[command.index(flag) + 1]


def _seconds(text: str) -> float:
    m = re.fullmatch(r"(\d+)(s|m)", str(text))
    assert m, text
    return float(m.group(1)) * (60 if m.group(2) == "m" else 1)


def _mount_targets(service: dict) -> list[str]:
    return [v.split(":")[1] for v in service.get("volumes", [])]


@pytest.fixture
def parser(monkeypatch):
    for k, v in ROBOT_ENV.items():
        monkeypatch.setenv(k, v)
    return build_parser()


@pytest.mark.parametrize("path", [COMPOSE, EUROC], ids=["default", "euroc"])
def test_compose_commands_exist_in_cli(path, parser) -> None:
    compose = _load(COMPOSE)
    services = compose["services"] if path == COMPOSE else _merged()
    assert {"cloud", "edge", "robot1", "robot2", "robot3"} <= set(services)
    if path == EUROC:
        assert {"robot4", "robot5"} <= set(services)
    for name, service in services.items():
        command = [_substitute(c) for c in service["command"]]
        assert command[0] == "recslam", name
        args = parser.parse_args(command[1:])  # SystemExit on an unknown command/flag
        assert callable(args.func), name
        for volume in service.get("volumes", []):
            source = volume.split(":", 1)[0]
            assert source in compose.get("volumes", {}) or source.startswith("."), volume


def test_every_environment_variable_is_read_by_the_code() -> None:
    sources = ENTRYPOINT.read_text() + "".join(
        p.read_text() for d in ("recslam", "services", "common") for p in (ROOT / d).rglob("*.py")
    )
    example = (ROOT / "docker" / "secret.env.example").read_text()
    env_file_vars = re.findall(r"^(\w+)=", example, flags=re.M)
    assert env_file_vars == ["RECSLAM_SECRET"]
    names = set(env_file_vars)
    for service in _merged().values():
        names |= set(service.get("environment", {}))
        assert service.get("env_file") == "docker/secret.env"
    assert {"SEQUENCE", "AGENT_ID", "NETEM"} <= names
    for name in names:
        assert re.search(rf"\b{name}\b", sources), f"{name} is set by compose but read nowhere"
    # The entrypoint maps the compose variables to what `recslam robot` reads.
    robot_cli = (ROOT / "recslam" / "commands" / "robot.py").read_text()
    for var in ROBOT_ENV:
        assert f"export {var}=" in ENTRYPOINT.read_text() and var in robot_cli, var


def test_ports_volumes_and_addresses_agree_with_the_flags() -> None:
    compose = _load(COMPOSE)
    s = compose["services"]
    cloud = [_substitute(c) for c in s["cloud"]["command"]]
    edge = [_substitute(c) for c in s["edge"]["command"]]
    cloud_port = _flag(cloud, "--listen").rsplit(":", 1)[1]
    edge_port = _flag(edge, "--listen").rsplit(":", 1)[1]
    # Dashboard: the published container port is the cloud's --dashboard-port.
    published = [_substitute(p).split(":")[-1] for p in s["cloud"]["ports"]]
    assert published == [_flag(cloud, "--dashboard-port")]
    # The edge reaches the cloud by service name and the cloud's port; robots reach the edge.
    assert _flag(edge, "--cloud") == f"cloud:{cloud_port}"
    assert f"RECSLAM_EDGE:-edge:{edge_port}" in ENTRYPOINT.read_text()
    # Healthchecks probe the listening ports.
    assert cloud_port == "7100" and cloud_port in " ".join(s["cloud"]["healthcheck"]["test"])
    assert edge_port in " ".join(s["edge"]["healthcheck"]["test"])
    # State, results and datasets live on mounts.
    for name, flag in (
        ("cloud", "--state-dir"),
        ("cloud", "--results"),
        ("edge", "--state-dir"),
        ("cloud", "--groundtruth"),
    ):
        command = cloud if name == "cloud" else edge
        path = _flag(command, flag)
        assert any(path.startswith(t) for t in _mount_targets(s[name])), (name, flag, path)
    for name, service in _merged().items():
        if name.startswith("robot"):
            assert "/datasets" in _mount_targets(service), name
            assert "NET_ADMIN" in service["cap_add"], name
            assert service["depends_on"]["edge"]["condition"] == "service_healthy"
            # restarts on a crash, a few times only: never a loop on a set-up error
            assert re.fullmatch(r"on-failure:[1-5]", service["restart"]), name
            assert _seconds(service["stop_grace_period"]) > 10, name  # the bounded flush
            env = service["environment"]  # ground truth is found by the agent's folder name
            assert env["AGENT_ID"] == env["SEQUENCE"].rsplit("/", 1)[1], name
    for name in ("cloud", "edge"):
        assert re.fullmatch(r"on-failure:[1-9]", s[name]["restart"]), name
    # The cloud's shutdown (last optimisation, full BA, MBP, outputs) outlasts Docker's 10 s.
    assert _seconds(s["cloud"]["stop_grace_period"]) >= 60
    # Folders the services write are handed to the container user by the entrypoint.
    for name, target in (("cloud", "/results"), ("edge", "/results"), ("dataset", "/datasets")):
        assert target in _mount_targets(s[name]), name
        assert s[name]["environment"]["RECSLAM_WRITABLE"] == target, name
    for volume in ("cloud-state", "edge-state"):
        assert volume in compose["volumes"]


def test_dockerfile_and_entrypoint() -> None:
    docker = (ROOT / "Dockerfile").read_text()
    assert docker.startswith("#") and "FROM python:3.11-slim\n" in docker
    assert "pip install --no-cache-dir" in docker and "-c requirements.lock ." in docker
    assert "iproute2" in docker and "useradd" in docker
    assert (
        "install -y --no-install-recommends iproute2 " in docker
    )  # no libgl1: nothing links it (cv2 headless, pycolmap, gtsam)
    for arg in ("PIP_INDEX", "PIP_EXTRA_INDEX", "PIP_TRUSTED"):
        assert f"ARG {arg}" in docker
        assert arg in _load(COMPOSE)["x-recslam"]["build"]["args"]
    assert "COPY docker/ca-certificates/" in docker
    entry = ENTRYPOINT.read_text()
    assert "tc qdisc replace dev" in entry and "${NETEM}" in entry
    assert "setpriv --reuid=recslam" in entry  # services never run as root


def test_ignore_files_keep_secrets_and_data_out() -> None:
    gitignore = (ROOT / ".gitignore").read_text().split()
    assert {"docker/secret.env", "/datasets/", "/out/"} <= set(gitignore)
    dockerignore = (ROOT / ".dockerignore").read_text().split()
    assert {".git", ".venv", "datasets", "data", "out", "docker/secret.env"} <= set(dockerignore)
    # "data" in .dockerignore is the top-level folder only: the package common/data is copied.
    assert "common/data" not in dockerignore and "**/data" not in dockerignore


def test_host_network_override(parser) -> None:
    """docker-compose.hostnet.yml: the same services on 127.0.0.1, ports from the environment."""
    over = _load(ROOT / "docker-compose.hostnet.yml")["services"]
    assert set(over) == set(_load(COMPOSE)["services"])
    assert all(s["network_mode"] == "host" for s in over.values())
    cloud = [_substitute(c) for c in over["cloud"]["command"]]
    edge = [_substitute(c) for c in over["edge"]["command"]]
    for command in (cloud, edge):
        assert callable(parser.parse_args(command[1:]).func)
    assert _flag(edge, "--cloud") == _flag(cloud, "--listen") == "127.0.0.1:7100"
    robot_env = over["robot1"]["environment"]
    assert _substitute(robot_env["EDGE"]) == _flag(edge, "--listen")
    assert robot_env["RECSLAM_HOST_NETWORK"] == "1"  # the entrypoint then refuses NETEM


def _entrypoint(tmp_path: Path, tc_output: str, **env: str):
    """Run docker/entrypoint.sh (not as root: no setpriv) with a fake tc that fails with
    ``tc_output``; the command is ``true``."""
    import os
    import subprocess

    fake = tmp_path / "bin"
    fake.mkdir(parents=True)
    (fake / "tc").write_text(f"#!/bin/sh\necho '{tc_output}' >&2\nexit 2\n")
    (fake / "tc").chmod(0o755)
    environ = {"PATH": f"{fake}:{os.environ['PATH']}", **env}
    return subprocess.run(
        ["sh", str(ENTRYPOINT), "true"], env=environ, capture_output=True, text=True, check=False
    )


def test_entrypoint_names_a_kernel_without_netem(tmp_path) -> None:
    out = _entrypoint(tmp_path, "Error: Specified qdisc kind is unknown.", NETEM="rate 100kbit")
    assert out.returncode == 78  # EX_CONFIG: restart on-failure:N gives up
    assert "has no netem qdisc" in out.stderr and "NET_ADMIN" not in out.stderr
    out = _entrypoint(
        tmp_path / "b", "RTNETLINK answers: Operation not permitted", NETEM="rate 1mbit"
    )
    assert out.returncode == 78 and "cap_add: [NET_ADMIN]" in out.stderr


def test_entrypoint_refuses_netem_on_the_host_network(tmp_path) -> None:
    out = _entrypoint(tmp_path, "unused", NETEM="rate 100kbit", RECSLAM_HOST_NETWORK="1")
    assert out.returncode == 78 and "host's network" in out.stderr


def test_secure_override_gives_each_service_only_its_own_key_file(tmp_path) -> None:
    """docker-compose.secure.yml: every service reads its own key file (issued under the names
    scripts/make-keys-and-tls.sh gives them), none gets the operator secret, both links use
    TLS with one certificate whose names cover the compose and host-network addresses."""
    from common.protocol.credentials import issue_keys, read_key_file
    from common.transport.tls import make_self_signed

    over = _load(ROOT / "docker-compose.secure.yml")["services"]
    assert set(over) == {"cloud", "edge", "robot1", "robot2", "robot3"}
    keys = tmp_path / "keys"
    issued = {p.name for p in issue_keys(keys, ["edge"], ["robot0", "robot1", "robot2"])}
    base = _load(COMPOSE)["services"]
    seen = set()
    for name, service in over.items():
        env = service["environment"]
        assert env["RECSLAM_SECRET"] == ""  # the operator secret reaches no container
        key_file = env["RECSLAM_KEY_FILE"].removeprefix("/keys/")
        assert key_file in issued and key_file not in seen
        seen.add(key_file)
        keyring = read_key_file(keys / key_file)
        if name.startswith("robot"):
            agent = base[name]["environment"]["AGENT_ID"]
            assert keyring.own is not None and keyring.own.agent_id == agent
            assert keyring.role_keys == () and keyring.operator is None
        assert env["RECSLAM_TLS_CA"] == "/tls/cert.pem"
        assert {"/keys", "/tls"} <= set(_mount_targets(service))
        # the override's volumes replace the base file's: every base mount is still there
        assert set(_mount_targets(base[name])) <= set(_mount_targets(service))
    for name in ("cloud", "edge"):
        assert over[name]["environment"]["RECSLAM_TLS_CERT"] == "/tls/cert.pem"
    script = (ROOT / "scripts" / "make-keys-and-tls.sh").read_text()
    for host in ("cloud", "edge", "localhost", "127.0.0.1"):
        assert f"--name {host}" in script
    cert, key = make_self_signed(tmp_path / "tls", ["cloud", "edge", "localhost", "127.0.0.1"])
    from common.transport.tls import TlsFiles

    assert TlsFiles(cert, key, cert).server_context() is not None
    gitignore = (ROOT / ".gitignore").read_text().split()
    assert {"/keys/", "/tls/"} <= set(gitignore)


def test_containers_give_up_on_an_unreachable_peer_and_flush_within_their_grace(parser) -> None:
    """Robots and the edge exit (non-zero, one line why) after --give-up-after without a
    session upstream, so restart caps apply instead of a silent wait; the edge's bounded
    flush at stop fits in its stop_grace_period."""
    services = _merged()
    for name, service in services.items():
        if name in ("cloud", "dataset"):
            continue
        args = parser.parse_args([_substitute(c) for c in service["command"]][1:])
        assert args.give_up_after > 0, name  # 0 would wait for ever
        assert str(service["restart"]).startswith("on-failure:"), name
    edge = _load(COMPOSE)["services"]["edge"]
    args = parser.parse_args([_substitute(c) for c in edge["command"]][1:])
    assert args.stop_flush_timeout < _seconds(edge["stop_grace_period"])


def test_sites_override_runs_two_edges_and_a_robot_that_moves(parser) -> None:
    """docker-compose.sites.yml: a second edge with its own identity, state and stats, three
    robots on it, one of which hands over to the first edge; every command parses."""
    base = _load(COMPOSE)
    sites = _load(ROOT / "docker-compose.sites.yml")
    services = {k: dict(v) for k, v in base["services"].items()}
    for name, over in sites["services"].items():
        services[name] = {**services.get(name, {}), **over}
    commands = {n: [_substitute(c) for c in s["command"]] for n, s in services.items()}
    for name, command in commands.items():
        assert callable(parser.parse_args(command[1:]).func), name
    edges = {n: c for n, c in commands.items() if c[2] == "edge"}
    assert set(edges) == {"edge", "edge-b"}
    ids = {n: _flag(c, "--agent-id") if "--agent-id" in c else "edge" for n, c in edges.items()}
    assert len(set(ids.values())) == 2  # the cloud tells the edges apart by their ids
    for flag in ("--state-dir", "--stats-out"):
        assert len({_flag(c, flag) for c in edges.values()}) == 2, flag
    assert {_flag(c, "--cloud") for c in edges.values()} == {_flag(commands["edge"], "--cloud")}
    b = services["edge-b"]
    assert "edge-b-state" in sites["volumes"]
    assert _flag(edges["edge-b"], "--state-dir").startswith("/state")
    assert "edge-b-state:/state" in b["volumes"]
    assert b["environment"]["RECSLAM_WRITABLE"] == "/results" and "/results" in _mount_targets(b)
    port = _flag(edges["edge-b"], "--listen").rsplit(":", 1)[1]
    assert port in " ".join(b["healthcheck"]["test"])
    # Robots: unique ids, each on an edge service it waits for; the moving robot's handover
    # target is the other edge's address.
    robots = {n: s for n, s in services.items() if n.startswith("robot")}
    agent_ids = [s["environment"]["AGENT_ID"] for s in robots.values()]
    assert len(agent_ids) == len(set(agent_ids)) == 6
    n_robots = int(_flag(commands["dataset"], "--robots"))
    for name, s in robots.items():
        env = s["environment"]
        edge = env.get("EDGE", "edge:7000").split(":")[0]
        assert edge in edges and s["depends_on"][edge]["condition"] == "service_healthy", name
        assert int(env["SEQUENCE"].rsplit("robot", 1)[1]) < n_robots, name
        if "--handover" in commands[name]:
            target = _flag(commands[name], "--handover").split("=", 1)[1].split(":")[0]
            assert target in edges and target != edge, name
            assert s["depends_on"][target]["condition"] == "service_healthy", name
    assert sum("--handover" in commands[n] for n in robots) == 1
