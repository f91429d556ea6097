"""common.folders: a folder a service cannot write is one line naming it, at start."""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import pytest

from common.folders import FolderError, writable_folder


def test_creates_missing_folders(tmp_path) -> None:
    folder = writable_folder(tmp_path / "a" / "b", "--results")
    assert folder.is_dir() and list(folder.iterdir()) == []  # the probe file is gone


def test_a_file_is_not_a_folder(tmp_path) -> None:
    (tmp_path / "f").write_text("x")
    with pytest.raises(FolderError, match=r"^--out .*/f: exists and is not a folder$"):
        writable_folder(tmp_path / "f", "--out")


def _as_nobody(target: Path) -> str:
    """writable_folder(target) in a forked child running as uid/gid 65534: its error line."""
    read, write = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: drop root, try, report, exit without pytest's teardown
        code = 1
        try:
            os.setgid(65534)
            os.setuid(65534)
            writable_folder(target, "--results")
        except FolderError as exc:
            os.write(write, str(exc).encode())
            code = 2
        finally:
            os._exit(code)
    os.close(write)
    with os.fdopen(read) as f:
        line = f.read()
    _, status = os.waitpid(pid, 0)
    assert os.waitstatus_to_exitcode(status) == 2, line
    return line


def test_unwritable_folder_names_folder_owner_and_uid(tmp_path) -> None:
    """As a user who may not write: uid 65534 when the tests run as root (whom no mode stops),
    else this user on a mode-555 folder."""
    if os.getuid() != 0:
        folder = tmp_path / "ro"
        folder.mkdir(mode=0o555)
        with pytest.raises(FolderError, match=rf"--results {folder}: not writable by uid"):
            writable_folder(folder, "--results")
        return
    base = Path(tempfile.mkdtemp(dir="/tmp", prefix="recslam-folders-"))
    try:
        base.chmod(0o755)
        (base / "results").mkdir(mode=0o755)
        for target, words in (
            (base / "results", "not writable"),
            (base / "new" / "x", "cannot create it"),
        ):
            line = _as_nobody(target)
            assert line.startswith(f"--results {target}: {words}") and "\n" not in line
            assert "by uid 65534 (owner uid 0, mode 755" in line
    finally:
        shutil.rmtree(base)
