"""The placeholder of docker/secret.env.example is refused as a secret, with the way out."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from common.protocol.credentials import PLACEHOLDER_SECRET, CredentialsError, load_secret

EXAMPLE = Path(__file__).resolve().parents[2] / "docker" / "secret.env.example"


def test_the_example_file_holds_the_placeholder() -> None:
    (value,) = re.findall(r"^RECSLAM_SECRET=(.*)$", EXAMPLE.read_text(), flags=re.M)
    assert value.encode() == PLACEHOLDER_SECRET


def test_placeholder_refused_from_environment_and_file(tmp_path) -> None:
    with pytest.raises(CredentialsError, match=r"^\$RECSLAM_SECRET: this is the placeholder"):
        load_secret(None, {"RECSLAM_SECRET": PLACEHOLDER_SECRET.decode()})
    f = tmp_path / "secret"
    f.write_bytes(PLACEHOLDER_SECRET + b"\n")
    with pytest.raises(CredentialsError, match=r"make docker/secret\.env"):
        load_secret(f)


def test_a_real_secret_passes() -> None:
    assert load_secret(None, {"RECSLAM_SECRET": "x" * 32}) == b"x" * 32
