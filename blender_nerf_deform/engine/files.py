"""Writing files so that nothing the user made is ever half-written (DESIGN.md, conventions)."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import BinaryIO, Callable

import numpy as np

from .errors import EngineError


def _process_umask() -> int:
    # Read once (os.umask can only be read by setting it); files get the permissions a plain
    # open() would give them, not mkstemp's owner-only 0600, so renders on a shared farm
    # folder stay readable by the rest of the pipeline.
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


_UMASK = _process_umask()


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
        try:
            mode = path.stat().st_mode & 0o7777  # replacing a file keeps its permissions
        except FileNotFoundError:
            mode = 0o666 & ~_UMASK
        os.chmod(tmp, mode)
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


def write_png_rgba(path, rgba: np.ndarray) -> None:
    """Write an (H, W, 4) float straight-alpha image as an 8-bit RGBA PNG, atomically."""
    from PIL import Image

    arr = (np.clip(rgba, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    atomic_write(path, lambda f: Image.fromarray(arr, mode="RGBA").save(f, format="PNG"))
