"""Folders a service writes into: checked once at start, with one line naming the folder.

A service that finds its result or state folder unwritable (a bind mount Docker created as
root, a folder of another user) must say so when it starts, not with a ``PermissionError``
traceback at its first write or at shutdown. :func:`writable_folder` creates the folder when
missing and proves it writable by creating (and removing) a file in it.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from common.errors import RecslamError


class FolderError(RecslamError, OSError):
    """A folder a service must write into cannot be created or written."""


def _owner(path: Path) -> str:
    try:
        st = path.stat()
    except OSError:
        return "owner unknown"
    return f"owner uid {st.st_uid}, mode {st.st_mode & 0o777:o}"


def _uid() -> str:
    return f"uid {os.getuid()}" if hasattr(os, "getuid") else "this user"


def writable_folder(path: str | Path, what: str) -> Path:
    """Create ``path`` (with its parents) if missing and check this process can write into it.

    ``what`` names the folder's role in the message (e.g. ``"--results"``). Raises FolderError
    with one line naming the folder, its owner and this process's uid."""
    folder = Path(path)
    if folder.exists() and not folder.is_dir():
        raise FolderError(f"{what} {folder}: exists and is not a folder")
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        parent = next((p for p in folder.parents if p.exists()), folder)
        raise FolderError(
            f"{what} {folder}: cannot create it ({exc.strerror}): {parent} is not writable "
            f"by {_uid()} ({_owner(parent)}); chown it or choose another folder"
        ) from None
    try:
        with tempfile.TemporaryFile(dir=folder, prefix=".recslam-write-check-"):
            pass
    except OSError as exc:
        raise FolderError(
            f"{what} {folder}: not writable by {_uid()} ({_owner(folder)}; {exc.strerror}); "
            "chown it or choose another folder"
        ) from None
    return folder
