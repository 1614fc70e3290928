"""Files under the data folder, written atomically (temporary file + fsync + rename + fsync dir).

A reader sees either the whole old file or the whole new one, and a file that was reported
written survives a crash (kill -9, power loss on a journalling file system). Paths handed out
are relative to the data folder so the folder can move.
"""

from __future__ import annotations

import contextlib
import os
import uuid
from pathlib import Path


class FileStore:
    """The service's data folder. Tenant data lives under ``tenants/<tenant id>/``."""

    def __init__(self, root: Path) -> None:
        self.root = Path(root)
        self.root.mkdir(parents=True, exist_ok=True)

    def path(self, relative: str) -> Path:
        """Absolute path of a stored file; refuses anything that leaves the data folder."""
        resolved = (self.root / relative).resolve()
        if not resolved.is_relative_to(self.root.resolve()):
            raise ValueError(f"path {relative!r} leaves the data folder")
        return resolved

    def write(self, relative: str, data: bytes) -> str:
        """Write ``data`` atomically and durably; returns ``relative``."""
        target = self.path(relative)
        target.parent.mkdir(parents=True, exist_ok=True)
        tmp = target.with_name(f".{target.name}.{uuid.uuid4().hex}.tmp")
        try:
            with tmp.open("wb") as handle:
                handle.write(data)
                handle.flush()
                os.fsync(handle.fileno())
            os.replace(tmp, target)
        finally:
            with contextlib.suppress(FileNotFoundError):
                tmp.unlink()
        _fsync_dir(target.parent)
        return relative

    def read(self, relative: str) -> bytes:
        return self.path(relative).read_bytes()

    def exists(self, relative: str) -> bool:
        return self.path(relative).is_file()

    def delete(self, relative: str) -> None:
        with contextlib.suppress(FileNotFoundError):
            self.path(relative).unlink()

    def writable(self) -> bool:
        return os.access(self.root, os.W_OK)


def _fsync_dir(directory: Path) -> None:
    """Make the rename itself durable (POSIX); a no-op where directories cannot be opened."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def tenant_path(tenant_id: str, *parts: str) -> str:
    return "/".join(("tenants", tenant_id, *parts))
