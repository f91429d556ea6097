"""Check what a ``docker compose up`` run of recslam left behind (used by compose-test.sh).

``python3 scripts/compose_check.py drained RESULTS`` exits 0 once the edge processed every
frame it decoded and queues nothing (``edge-stats.json``), 1 otherwise: the test polls it.

``python3 scripts/compose_check.py outputs RESULTS DATASET ROBOT... [--max-joint-ate M]``
checks the cloud's result folder ``RESULTS`` (``./out/compose``) after the stack stopped:

- ``trajectories/<robot>.tum`` for every robot, with at least 2 poses;
- ``eval/ate.md`` and ``eval/ate.json``; the joint row only when ``cloud_maps.json`` says all
  robots share one map, else the "Maps did not merge" line;
- every frame of each robot's sequence (``DATASET/<robot>/mav0/cam0/data.csv``) decoded
  exactly once at the edge (``edge-stats.json``: ``frames_decoded`` equal to the frame count;
  a duplicate would count twice, a loss once less);
- with ``--max-joint-ate M``: one map, and its joint ATE RMSE (``eval/ate.json``) at most M
  metres (swarm-test.sh).

It prints one line per check and a summary; exit code 0 when every check passed. Standard
library only: it runs with the host's python3, outside the image.

``python3 scripts/compose_check.py strip-ports CONFIG`` rewrites a resolved compose file
(``docker-compose config``) without the published ports of services on the host network:
docker-compose 1.x (Debian bookworm's) refuses ports with ``network_mode: host``, which
Compose v2 and the engine accept (and ignore). Needs PyYAML (python3-yaml, a dependency of
Debian's docker-compose).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any


def _load(path: Path) -> dict[str, Any]:
    data = json.loads(path.read_text())
    if not isinstance(data, dict):
        raise ValueError(f"{path}: not a JSON object")
    return data


def drained(results: Path) -> bool:
    """True when the edge's counters show every decoded frame processed and nothing queued."""
    try:
        robots = _load(results / "edge-stats.json").get("robots", {})
    except (OSError, ValueError):
        return False
    return bool(robots) and all(
        r.get("frames_processed", 0) >= r.get("frames_decoded", 0) and not r.get("queued")
        for r in robots.values()
    )


def _frames_in(dataset: Path, robot: str) -> int:
    csv = dataset / robot / "mav0" / "cam0" / "data.csv"
    lines = [ln for ln in csv.read_text().splitlines() if ln.strip() and not ln.startswith("#")]
    return len(lines)


def check_outputs(
    results: Path, dataset: Path, robots: list[str], max_joint_ate: float | None = None
) -> list[tuple[bool, str]]:
    """(passed, line) for every check of the module docstring."""
    out: list[tuple[bool, str]] = []
    for robot in robots:
        tum = results / "trajectories" / f"{robot}.tum"
        poses = len(tum.read_text().splitlines()) if tum.is_file() else 0
        out.append((poses >= 2, f"trajectory {tum.relative_to(results)}: {poses} poses"))
    maps = _load(results / "cloud_maps.json") if (results / "cloud_maps.json").is_file() else {}
    joint_frame = bool(maps.get("joint_frame"))
    out.append((bool(maps), f"cloud_maps.json: maps {maps.get('maps')}, one frame {joint_frame}"))
    ate_md = results / "eval" / "ate.md"
    text = ate_md.read_text() if ate_md.is_file() else ""
    has_joint = "| **joint** |" in text
    if not text:
        out.append((False, "eval/ate.md: missing"))
    elif joint_frame:
        row = next((ln for ln in text.splitlines() if ln.startswith("| **joint** |")), "")
        rmse = row.split("|")[3].strip() if row else "?"
        out.append((has_joint, f"eval/ate.md: joint ATE RMSE {rmse} m (one map)"))
    else:
        said = "Maps did not merge" in text
        out.append((said and not has_joint, "eval/ate.md: maps did not merge, no joint row"))
    ate_json = results / "eval" / "ate.json"
    if ate_json.is_file():
        ate = _load(ate_json)
        agents = ate.get("agents", {})
        per = ", ".join(
            f"{a} {agents[a]['individual']['stats_m']['rmse']:.4f} m" for a in sorted(agents)
        )
        out.append((set(agents) == set(robots), f"eval/ate.json: per-robot ATE RMSE {per}"))
        if max_joint_ate is not None:
            joint = float(ate.get("joint", {}).get("stats_m", {}).get("rmse", "nan"))
            one_map = bool(ate.get("joint_frame")) and joint_frame
            out.append(
                (
                    one_map and joint <= max_joint_ate,
                    f"joint ATE {joint:.4f} m <= {max_joint_ate} m, one map {one_map}",
                )
            )
    else:
        out.append((False, "eval/ate.json: missing"))
    edge = _load(results / "edge-stats.json").get("robots", {})
    for robot in robots:
        want = _frames_in(dataset, robot)
        got = edge.get(robot, {}).get("frames_decoded", 0)
        out.append((got == want, f"{robot}: {got} of {want} frames decoded at the edge"))
    return out


def strip_host_ports(config: Path) -> list[str]:
    """Remove ``ports`` of host-network services from the compose file ``config`` (in place);
    returns the services changed."""
    import yaml  # the host's python3-yaml (Debian's docker-compose needs it)

    data = yaml.safe_load(config.read_text())
    changed = []
    for name, service in data.get("services", {}).items():
        if service.get("network_mode") == "host" and service.pop("ports", None) is not None:
            changed.append(name)
    config.write_text(yaml.safe_dump(data, sort_keys=False))
    return changed


def main(argv: list[str]) -> int:
    if len(argv) == 2 and argv[0] == "strip-ports":
        changed = strip_host_ports(Path(argv[1]))
        sys.stdout.write(f"published ports dropped (host network): {', '.join(changed)}\n")
        return 0
    if len(argv) == 2 and argv[0] == "drained":
        return 0 if drained(Path(argv[1])) else 1
    max_joint_ate = None
    if len(argv) >= 2 and argv[-2] == "--max-joint-ate":
        max_joint_ate = float(argv[-1])
        argv = argv[:-2]
    if len(argv) >= 4 and argv[0] == "outputs":
        try:
            checks = check_outputs(Path(argv[1]), Path(argv[2]), argv[3:], max_joint_ate)
        except (OSError, ValueError, KeyError) as exc:
            sys.stderr.write(f"compose_check: cannot read the outputs: {exc}\n")
            return 1
        for ok, line in checks:
            sys.stdout.write(f"  {'ok  ' if ok else 'FAIL'} {line}\n")
        failed = sum(not ok for ok, _ in checks)
        sys.stdout.write(f"  {len(checks) - failed}/{len(checks)} checks passed\n")
        return 1 if failed else 0
    sys.stderr.write(
        "usage: compose_check.py drained RESULTS"
        " | outputs RESULTS DATASET ROBOT... [--max-joint-ate M]\n"
    )
    return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
