"""Atomic file writes: a reader never sees a half-written file, and a kill leaves only recognisable temporaries.

A file is written to a temporary beside it, fsynced, then renamed over the final name in one step. Temporaries
are hidden and end in ``.partial`` (``.<name>.<pid>.<random>.partial``), so no glob for a final file type
(``*.png``, ``*.lines.txt``, ``*.json``) matches one a kill left behind, and `remove_temporaries` finds them all.
Files get the mode `open()` would give them (0o666 minus the umask), not mkstemp's owner-only 0o600.
"""

from __future__ import annotations

import os
import secrets
from pathlib import Path

TEMPORARY_SUFFIX = ".partial"
TEMPORARY_GLOB = f".*{TEMPORARY_SUFFIX}"


def temporary_path(path: Path) -> Path:
    """A fresh temporary name beside `path`: hidden, unique per process and call, ending in TEMPORARY_SUFFIX."""
    return path.with_name(f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}{TEMPORARY_SUFFIX}")


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write `data` to `path` so that `path` is at every instant absent, the old file, or the whole new one."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temporary_path(path)
    # O_EXCL: never write into someone else's file; 0o666: the umask decides the mode, as with open().
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0), 0o666)
    try:
        with os.fdopen(fd, "wb") as handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())  # the bytes reach the disk before the name does
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    _fsync_folder(path.parent)


def atomic_write_text(path: str | Path, text: str) -> None:
    """atomic_write_bytes of UTF-8 text, newlines written as they are ("\\n" on every platform)."""
    atomic_write_bytes(path, text.encode("utf-8"))


def remove_temporaries(root: str | Path) -> list[Path]:
    """Delete every temporary under `root` (left by a killed writer); the deleted paths.
    Only call it while nothing writes under `root`: a live writer's temporary would go too."""
    removed = []
    for tmp in sorted(Path(root).rglob(TEMPORARY_GLOB)):
        if tmp.is_file():
            tmp.unlink(missing_ok=True)
            removed.append(tmp)
    return removed


def _fsync_folder(folder: Path) -> None:
    """Make a rename in `folder` durable, so that a later write (a manifest line) cannot outlive it in a crash."""
    if os.name != "posix":
        return  # folders cannot be opened for fsync on Windows
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
