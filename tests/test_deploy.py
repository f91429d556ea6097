"""Static checks of the multi-host deployments (issue 19, item 5): the Kubernetes manifests in
deploy/k8s and the Docker Swarm stack file agree with docker-compose.yml and with the command
line: every container's arguments parse with the real ``recslam`` parser, ports and addresses
meet, each workload mounts only its own key file and that file is one ``recslam keys new``
writes for its agent id. (Rendered and schema-validated in docs/deployment.md; the strict
model validation runs here when the ``kubernetes`` package is installed.)"""

from __future__ import annotations

import importlib.util
import re
import shutil
import subprocess
from pathlib import Path
from typing import Any

import pytest
import yaml

from common.protocol.credentials import issue_keys
from recslam.cli import build_parser

ROOT = Path(__file__).resolve().parents[1]
K8S = ROOT / "deploy" / "k8s"
SWARM = ROOT / "docker-compose.swarm.yml"
COMPOSE = ROOT / "docker-compose.yml"
NAMESPACE = "recslam"


def _docs() -> list[dict[str, Any]]:
    files = [p for p in sorted(K8S.glob("*.yaml")) if p.name != "kustomization.yaml"]
    return [d for p in files for d in yaml.safe_load_all(p.read_text()) if d]


def _of(kind: str) -> list[dict[str, Any]]:
    return [d for d in _docs() if d["kind"] == kind]


def _pod(workload: dict[str, Any]) -> dict[str, Any]:
    return workload["spec"]["template"]["spec"]


def _flag(args: list[str], flag: str) -> str:
    return args[args.index(flag) + 1]


def _port(address: str) -> int:
    return int(address.rsplit(":", 1)[1])


def _service(name_or_dns: str) -> dict[str, Any]:
    """The Service a ``NAME.NAMESPACE.svc`` (or bare NAME) address names."""
    name, *rest = name_or_dns.split(".")
    if rest:
        assert rest[:2] == [NAMESPACE, "svc"], name_or_dns
    found = [s for s in _of("Service") if s["metadata"]["name"] == name]
    assert len(found) == 1, name_or_dns
    return found[0]


def _container_port(container: dict[str, Any], name: str) -> int:
    return next(p["containerPort"] for p in container["ports"] if p["name"] == name)


def _key_secret(pod: dict[str, Any], key_file: str) -> tuple[str, str]:
    """(secret name, key in the secret) that the container's ``--key-file`` is read from."""
    mounts = {m["name"]: m["mountPath"] for m in pod["containers"][0]["volumeMounts"]}
    for volume in pod["volumes"]:
        secret = volume.get("secret")
        if secret is None or not key_file.startswith(mounts[volume["name"]] + "/"):
            continue
        inside = key_file[len(mounts[volume["name"]]) + 1 :]
        for item in secret.get("items", [{"key": inside, "path": inside}]):
            if item["path"] == inside:
                return secret["secretName"], item["key"]
    raise AssertionError(f"{key_file} is on no secret volume")


def _generated() -> dict[tuple[str, str], str]:
    """(secret name, key) -> the key file under deploy/k8s/ it is made from (kustomization)."""
    kustomization = yaml.safe_load((K8S / "kustomization.yaml").read_text())
    out = {}
    for gen in kustomization["secretGenerator"]:
        assert gen["namespace"] == NAMESPACE
        for entry in gen["files"]:
            key, path = entry.split("=")
            out[gen["name"], key] = path
    return out


@pytest.fixture(scope="module")
def issued(tmp_path_factory) -> set[str]:
    """The key file names `recslam keys new` writes for the manifests' edges and robots."""
    edges = [_flag(_pod(s)["containers"][0]["args"], "--agent-id") for s in _of("StatefulSet")]
    robots = [_flag(_pod(j)["containers"][0]["args"], "--agent-id") for j in _of("Job")]
    paths = issue_keys(tmp_path_factory.mktemp("keys"), edges, robots)
    return {p.name for p in paths}


def test_kustomization_lists_every_manifest_and_one_namespace() -> None:
    kustomization = yaml.safe_load((K8S / "kustomization.yaml").read_text())
    files = {p.name for p in K8S.glob("*.yaml")} - {"kustomization.yaml"}
    assert set(kustomization["resources"]) == files
    assert [d["metadata"]["name"] for d in _of("Namespace")] == [NAMESPACE]
    for doc in _docs():
        if doc["kind"] != "Namespace":
            assert doc["metadata"]["namespace"] == NAMESPACE, doc["metadata"]["name"]
    assert "/deploy/k8s/keys/" in (ROOT / ".gitignore").read_text().splitlines()


def test_every_container_runs_a_real_recslam_command_of_its_tier() -> None:
    parser = build_parser()
    image = yaml.safe_load(COMPOSE.read_text())["x-recslam"]["image"]
    tiers = {"Deployment": "cloud", "StatefulSet": "edge", "Job": "robot"}
    workloads = [d for d in _docs() if d["kind"] in tiers]
    assert sorted(d["kind"] for d in workloads) == ["Deployment", "Job", "Job", "Job"] + [
        "StatefulSet"
    ] * len(_of("StatefulSet"))
    for w in workloads:
        pod = _pod(w)
        (container,) = pod["containers"]
        assert container["image"] == image, w["metadata"]["name"]
        args = container["args"]
        assert args[0] == "recslam" and args[args.index("-v") + 1] == tiers[w["kind"]]
        parsed = parser.parse_args(args[1:])  # SystemExit on an option the CLI does not have
        assert callable(parsed.func)
        # the image's user (Dockerfile: useradd --uid 1000), never root
        ctx = pod["securityContext"]
        assert ctx["runAsNonRoot"] and ctx["runAsUser"] == ctx["fsGroup"] == 1000
        assert "--uid 1000 recslam" in (ROOT / "Dockerfile").read_text()


def test_one_cloud_and_its_ports_meet_the_edges_addresses() -> None:
    (cloud,) = _of("Deployment")
    assert cloud["spec"]["replicas"] == 1 and cloud["spec"]["strategy"]["type"] == "Recreate"
    container = _pod(cloud)["containers"][0]
    args = container["args"]
    assert _port(_flag(args, "--listen")) == _container_port(container, "link")
    assert int(_flag(args, "--dashboard-port")) == _container_port(container, "dashboard")
    compose = yaml.safe_load(COMPOSE.read_text())["services"]["cloud"]["command"]
    assert _flag(compose, "--listen") == _flag(args, "--listen")
    claims = {c["metadata"]["name"] for c in _of("PersistentVolumeClaim")}
    for volume in _pod(cloud)["volumes"]:
        if "persistentVolumeClaim" in volume:
            assert volume["persistentVolumeClaim"]["claimName"] in claims
    for edge in _of("StatefulSet"):
        e = _pod(edge)["containers"][0]
        target = _flag(e["args"], "--cloud")
        service = _service(target.rsplit(":", 1)[0])
        assert service["spec"]["selector"] == cloud["spec"]["selector"]["matchLabels"]
        (link,) = [p for p in service["spec"]["ports"] if p["port"] == _port(target)]
        assert link["targetPort"] == "link"
        # one edge per site, its journals on its own volume, its own Service
        assert edge["spec"]["replicas"] == 1
        assert edge["spec"]["serviceName"] == edge["metadata"]["name"]
        site = edge["spec"]["template"]["metadata"]["labels"]["recslam.example/site"]
        assert _pod(edge)["nodeSelector"]["recslam.example/site"] == site
        state = _flag(e["args"], "--state-dir")
        (claim,) = edge["spec"]["volumeClaimTemplates"]
        mounts = {m["name"]: m["mountPath"] for m in e["volumeMounts"]}
        assert state.startswith(mounts[claim["metadata"]["name"]] + "/")
        assert float(_flag(e["args"], "--give-up-after")) > 0


def test_robots_reach_their_sites_edge_and_read_their_own_sequence() -> None:
    edges = {s["metadata"]["name"]: s for s in _of("StatefulSet")}
    for job in _of("Job"):
        pod = _pod(job)
        args = pod["containers"][0]["args"]
        agent = _flag(args, "--agent-id")
        assert job["metadata"]["name"] == agent
        assert pod["restartPolicy"] == "Never" and 0 < job["spec"]["backoffLimit"] <= 5
        target = _flag(args, "--edge")
        service = _service(target.rsplit(":", 1)[0])
        edge = edges[service["metadata"]["name"]]
        assert service["spec"]["selector"] == edge["spec"]["selector"]["matchLabels"]
        edge_container = _pod(edge)["containers"][0]
        (port,) = [p for p in service["spec"]["ports"] if p["port"] == _port(target)]
        assert _container_port(edge_container, port["targetPort"]) == _port(
            _flag(edge_container["args"], "--listen")
        )
        mounts = {m["name"]: m["mountPath"] for m in pod["containers"][0]["volumeMounts"]}
        assert _flag(args, "--dataset").startswith(mounts["datasets"] + "/")
        assert _flag(args, "--dataset").endswith("/" + agent)
        assert float(_flag(args, "--give-up-after")) > 0


def test_each_workload_mounts_only_its_own_key_file(issued) -> None:
    generated = _generated()
    used = set()
    for w in [*_of("Deployment"), *_of("StatefulSet"), *_of("Job")]:
        pod = _pod(w)
        args = pod["containers"][0]["args"]
        tier = args[args.index("-v") + 1]
        secret, key = _key_secret(pod, _flag(args, "--key-file"))
        source = Path(generated[secret, key])
        want = {
            "cloud": "cloud.keys",
            "edge": f"edge-{_flag(args, '--agent-id')}.keys" if tier == "edge" else "",
            "robot": f"robot-{_flag(args, '--agent-id')}.keys" if tier == "robot" else "",
        }[tier]
        assert source.parent == Path("keys") and source.name == want, (w["metadata"], source)
        assert want in issued  # a file `recslam keys new` writes for that agent id
        secrets = [v["secret"]["secretName"] for v in pod["volumes"] if "secret" in v]
        assert secrets == [secret], w["metadata"]["name"]  # no other identity's key
        used.add(secret)
    assert used == {name for name, _ in generated}
    assert not any("operator" in path for path in generated.values())


def test_grace_periods_cover_the_bounded_flushes_and_match_compose() -> None:
    compose = yaml.safe_load(COMPOSE.read_text())["services"]
    (cloud,) = _of("Deployment")
    assert _pod(cloud)["terminationGracePeriodSeconds"] == int(
        str(compose["cloud"]["stop_grace_period"]).rstrip("s")
    )
    for w in [*_of("StatefulSet"), *_of("Job")]:
        pod = _pod(w)
        flush = float(_flag(pod["containers"][0]["args"], "--stop-flush-timeout"))
        assert pod["terminationGracePeriodSeconds"] > flush, w["metadata"]["name"]


def test_manifests_validate_against_the_kubernetes_clients_models(tmp_path) -> None:
    """Strict validation (unknown fields, types, required fields) of the manifests and of a
    generated Secret; needs the kubernetes client (not a dependency of recslam)."""
    if importlib.util.find_spec("kubernetes") is None:
        pytest.skip("the kubernetes package is not installed (pip install kubernetes)")
    spec = importlib.util.spec_from_file_location(
        "k8s_validate", ROOT / "scripts" / "k8s_validate.py"
    )
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    secret = {"apiVersion": "v1", "kind": "Secret", "metadata": {"name": "s"}, "data": {}}
    assert module.validate([*_docs(), secret]) == []
    broken = _of("Job")[0]
    broken["spec"]["template"]["spec"]["containers"][0]["imagePullPolicy"] = 3
    assert module.validate([broken])


def _swarm() -> dict[str, Any]:
    return yaml.safe_load(SWARM.read_text())


def _expand(value: Any, env: dict[str, str] | None = None) -> Any:
    """``${NAME:-default}`` in the stack file's strings (lists, dicts) as `docker stack deploy`
    interpolates them, from ``env`` (default: none set)."""
    env = env or {}
    if isinstance(value, str):
        return re.sub(r"\$\{(\w+):-([^}]*)\}", lambda m: env.get(m[1]) or m[2], value)
    if isinstance(value, list):
        return [_expand(v, env) for v in value]
    if isinstance(value, dict):
        return {k: _expand(v, env) for k, v in value.items()}
    return value


def test_swarm_stack_runs_the_compose_services_with_real_commands(monkeypatch) -> None:
    swarm, compose = _swarm(), yaml.safe_load(COMPOSE.read_text())
    assert set(swarm["services"]) == set(compose["services"]) - {"dataset"}
    for k, v in {"RECSLAM_DATASET": "/d", "RECSLAM_AGENT_ID": "r", "RECSLAM_EDGE": "e:1"}.items():
        monkeypatch.setenv(k, v)  # what the entrypoint exports for a robot
    parser = build_parser()
    for name, service in swarm["services"].items():
        assert service["image"] == "${RECSLAM_IMAGE:-recslam:latest}"
        command = _expand(service["command"])
        assert command[:2] == ["recslam", "-v"]
        assert callable(parser.parse_args(command[1:]).func), name
        # swarm ignores depends_on and restart: its own restart policy, a few attempts
        assert "depends_on" not in service and "restart" not in service
        policy = service["deploy"]["restart_policy"]
        assert policy["condition"] == "on-failure" and 0 < policy["max_attempts"] <= 5
        assert service["deploy"]["placement"]["constraints"], name
        if command[2] != "cloud":
            assert "--give-up-after" in command
    edge = _expand(swarm["services"]["edge"]["command"])
    cloud = _expand(swarm["services"]["cloud"]["command"])
    assert _flag(edge, "--cloud") == f"cloud:{_port(_flag(cloud, '--listen'))}"
    for robot in ("robot1", "robot2", "robot3"):
        env = _expand(swarm["services"][robot]["environment"])
        assert env["EDGE"] == f"edge:{_port(_flag(edge, '--listen'))}"
        assert env["SEQUENCE"] == compose["services"][robot]["environment"]["SEQUENCE"]
        # one label per robot, so that one node may carry several (as in make swarm-test)
        (where,) = swarm["services"][robot]["deploy"]["placement"]["constraints"]
        assert where == f"node.labels.recslam.robot.{env['AGENT_ID']} == true"


@pytest.mark.parametrize("network", ["", "host"])
def test_swarm_stack_runs_on_the_overlay_or_the_hosts_network(network: str) -> None:
    """By default the overlay "recslam" and service names; RECSLAM_SWARM_NETWORK=host (as
    scripts/swarm-test.sh deploys it) the node's own network, addresses and ports from the
    environment, the healthchecks and published ports on the same ports."""
    env = {"RECSLAM_SWARM_NETWORK": network}
    if network:
        env |= {"LISTEN_HOST": "127.0.0.1", "CLOUD_HOST": "127.0.0.1", "EDGE_HOST": "127.0.0.1"}
        env |= {"CLOUD_PORT": "4100", "EDGE_PORT": "4000", "DASHBOARD_PORT": "4080"}
    swarm = _expand(_swarm(), env)
    services = swarm["services"]
    (net,) = {n for s in services.values() for n in s["networks"]}
    cloud, edge = services["cloud"], services["edge"]
    cloud_at, edge_at = _flag(cloud["command"], "--listen"), _flag(edge["command"], "--listen")
    if network:
        assert net == "host" and swarm["networks"]["host"] == {"external": True, "name": "host"}
        assert cloud_at == "127.0.0.1:4100" and edge_at == "127.0.0.1:4000"
        assert _flag(edge["command"], "--cloud") == "127.0.0.1:4100"
    else:
        assert net == "recslam" and swarm["networks"]["recslam"]["driver"] == "overlay"
        assert cloud_at == "0.0.0.0:7100" and edge_at == "0.0.0.0:7000"
        assert _flag(edge["command"], "--cloud") == "cloud:7100"
    for name, service in services.items():
        if name.startswith("robot"):
            assert service["environment"]["EDGE"].endswith(f":{_port(edge_at)}")
    for service, port in ((cloud, _port(cloud_at)), (edge, _port(edge_at))):
        assert f"('127.0.0.1', {port})" in service["healthcheck"]["test"][-1]
    dashboard = int(_flag(cloud["command"], "--dashboard-port"))
    assert [(int(p["target"]), int(p["published"])) for p in cloud["ports"]] == [(dashboard,) * 2]
    assert [(int(p["target"]), int(p["published"])) for p in edge["ports"]] == [
        (_port(edge_at),) * 2
    ]


def test_swarm_services_get_only_their_own_key_file_as_a_secret(tmp_path) -> None:
    swarm = _swarm()
    agents = {"cloud": None, "edge": "edge"}
    for robot in ("robot1", "robot2", "robot3"):
        agents[robot] = swarm["services"][robot]["environment"]["AGENT_ID"]
    edge_id = _flag(swarm["services"]["edge"]["command"], "--agent-id")
    robots = [a for n, a in agents.items() if n.startswith("robot") and a]
    issued = {p.name for p in issue_keys(tmp_path, [edge_id], robots)}
    for name, service in swarm["services"].items():
        (secret,) = service["secrets"]
        assert service["environment"]["RECSLAM_KEY_FILE"] == f"/run/secrets/{secret['target']}"
        assert secret["uid"] == "1000" and secret["mode"] == 0o400  # the container user only
        source = Path(swarm["secrets"][secret["source"]]["file"])
        want = (
            "cloud.keys"
            if name == "cloud"
            else f"edge-{edge_id}.keys"
            if name == "edge"
            else f"robot-{agents[name]}.keys"
        )
        assert source == Path("keys") / want and want in issued, name


def test_docker_stack_config_accepts_the_swarm_file(tmp_path) -> None:
    docker = shutil.which("docker")
    if docker is None:
        pytest.skip("no docker CLI")
    help_text = subprocess.run(
        [docker, "stack", "config", "--help"], capture_output=True, text=True
    )
    if help_text.returncode != 0:
        pytest.skip("this docker CLI has no `docker stack config`")
    for network in ("", "host"):
        out = subprocess.run(
            [docker, "stack", "config", "-c", str(SWARM)],
            capture_output=True,
            text=True,
            timeout=60,
            cwd=tmp_path,
            env={"PATH": "/usr/bin:/bin", "RECSLAM_SWARM_NETWORK": network},
        )
        assert out.returncode == 0, out.stderr
        rendered = yaml.safe_load(out.stdout)
        assert rendered["services"]["cloud"]["stop_grace_period"] in ("2m0s", "120s")
        assert set(rendered["secrets"]) == set(_swarm()["secrets"])
        assert list(rendered["services"]["edge"]["networks"]) == [network or "recslam"]
