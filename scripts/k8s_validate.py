"""Validate Kubernetes manifests offline, strictly, against the kubernetes Python client's models.

    python scripts/k8s_validate.py rendered.yaml [more.yaml ...]   # e.g. kubectl kustomize output

Where kubeconform cannot fetch its JSON schemas (no access to GitHub) and kubectl has no API
server to ask, the official client's generated models still describe every field of every
built-in kind: in the client used here (37.0.2) they are pydantic models that forbid unknown
fields. Each
document is validated, in pydantic's strict mode, against the model of its
``apiVersion``/``kind`` (``apps/v1`` ``Deployment`` -> ``V1Deployment``): an unknown or
misspelt field, a value of the wrong type (a string where an integer belongs) or a required
field left out is reported with its path.

``--write-schemas DIR`` also writes each kind's JSON schema (pydantic's, by JSON name) as
kubeconform names its files, so kubeconform validates offline too::

    python scripts/k8s_validate.py --write-schemas schemas rendered.yaml
    kubeconform -strict -summary \
        -schema-location 'schemas/{{ .ResourceKind }}{{ .KindSuffix }}.json' rendered.yaml

Needs the ``kubernetes`` package (``pip install kubernetes``, a version with pydantic models;
not a dependency of recslam). Exit code 0 when every document is valid, 1 otherwise (the
problems are printed).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import yaml


def model_name(api_version: str, kind: str) -> str:
    """``apps/v1``, ``Deployment`` -> ``V1Deployment``; ``batch/v1``, ``Job`` -> ``V1Job``."""
    version = api_version.split("/")[-1]
    return version[0].upper() + version[1:] + kind


def schema_file(api_version: str, kind: str) -> str:
    """kubeconform's file name of a kind's schema: ``deployment-apps-v1.json``,
    ``job-batch-v1.json``, ``service-v1.json`` (the group's first label, the version)."""
    group, _, version = api_version.rpartition("/")
    suffix = f"-{group.split('.')[0]}-{version}" if group else f"-{version}"
    return f"{kind.lower()}{suffix}.json"


def write_schemas(docs: list[dict[str, Any]], out: Path) -> list[Path]:
    """The JSON schema of every kind in ``docs``, from the client's models, into ``out``."""
    from kubernetes.client import models

    out.mkdir(parents=True, exist_ok=True)
    written = []
    for api, kind in sorted({(str(d["apiVersion"]), str(d["kind"])) for d in docs}):
        cls = getattr(models, model_name(api, kind))
        path = out / schema_file(api, kind)
        path.write_text(json.dumps(cls.model_json_schema(by_alias=True)))
        written.append(path)
    return written


def validate(docs: list[dict[str, Any]]) -> list[str]:
    """Problems of every document (``Kind/name: what``), [] when all are valid."""
    from kubernetes.client import models
    from pydantic import ValidationError

    problems: list[str] = []
    for doc in docs:
        kind, api = doc.get("kind", "?"), doc.get("apiVersion", "?")
        where = f"{kind}/{doc.get('metadata', {}).get('name', '?')}"
        cls = getattr(models, model_name(api, kind), None)
        if cls is None:
            problems.append(f"{where}: no model for {api} {kind} in the kubernetes client")
            continue
        try:
            cls.model_validate(doc, strict=True)
        except ValidationError as exc:
            for err in exc.errors():
                path = ".".join(str(p) for p in err["loc"])
                problems.append(f"{where}: {path}: {err['msg']}")
    return problems


def main(argv: list[str]) -> int:
    schemas = None
    if argv[:1] == ["--write-schemas"]:
        schemas, argv = Path(argv[1]), argv[2:]
    docs = [d for path in argv for d in yaml.safe_load_all(Path(path).read_text()) if d]
    if schemas is not None:
        for path in write_schemas(docs, schemas):
            print(f"wrote {path}")
    problems = validate(docs)
    for line in problems:
        print(line)
    kinds = sorted({str(d.get("kind")) for d in docs})
    print(json.dumps({"documents": len(docs), "kinds": kinds, "problems": len(problems)}))
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
