"""Writing files so that nothing the user made is ever half-written (DESIGN.md, conventions)."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import BinaryIO, Callable

from .errors import EngineError


def atomic_write(path: str | os.PathLike, write: Callable[[BinaryIO], None]) -> None:
    """Write `path` through `write(f)` into a temporary file beside it, flushed to disk, then
    rename it over `path`: an interrupted write leaves the previous file (or none), never a
    broken one. The folder must exist."""
    path = Path(path)
    if not path.parent.is_dir():
        raise EngineError(f"cannot write {path}: folder {path.parent} does not exist")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
