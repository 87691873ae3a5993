"""Writing files so that nothing the user made is ever half-written (docs/ARCHITECTURE.md, Conventions).

- `atomic_write`: a temporary file beside the target, flushed, then renamed over it; a full
  disk or a read-only folder is one EngineError naming the file, and Ctrl-C waits until the
  rename is done (a second Ctrl-C during the final checkpoint must not lose it).
- `StagedFiles`: several files written as one (a bake's frames): all of them take their place at
  the end, or none does, and the files they would have replaced stay as they were.
- `check_writable`: probe an output's folder before minutes of work go into it.
- `folder_lock`: one process at a time in a run folder (fcntl.flock: the kernel releases it
  when its process dies, so a crash never leaves a lock that blocks the next run).
- `remove_stale_temporaries`: what a killed process left of an atomic write.
"""

from __future__ import annotations

import contextlib
import errno
import os
import signal
import tempfile
import threading
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO

from .errors import EngineError


def _process_umask() -> int:
    # Read once (os.umask can only be read by setting it); files get the permissions a plain
    # open() would give them, not mkstemp's owner-only 0600, so renders on a shared farm
    # folder stay readable by the rest of the pipeline.
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


_UMASK = _process_umask()
_DISK_FULL = {errno.ENOSPC, getattr(errno, "EDQUOT", errno.ENOSPC)}


def write_error(path, exc: OSError) -> EngineError:
    """The one-line error of a failed write of `path`: a full disk says so."""
    if exc.errno in _DISK_FULL:
        return EngineError(f"cannot write {path}: the disk is full ({exc.strerror}); free some space and run again")
    return EngineError(f"cannot write {path}: {exc.strerror or exc}")


@contextlib.contextmanager
def interrupts_deferred():
    """Ctrl-C (SIGINT) inside the block is held until the block ends, then delivered as it would
    have been; so are SIGTERM and SIGHUP where a Python handler takes them (the command line's:
    errors.Terminated). Only the main thread can handle signals; elsewhere the block runs as is."""
    if threading.current_thread() is not threading.main_thread() or signal.getsignal(signal.SIGINT) is None:
        yield  # None: a handler installed outside Python, which could not be put back
        return
    held = [signal.SIGINT] + [
        getattr(signal, name)
        for name in ("SIGTERM", "SIGHUP")
        if hasattr(signal, name) and callable(signal.getsignal(getattr(signal, name)))
    ]
    received = []
    previous = {
        signum: signal.signal(signum, lambda signum, frame: received.append((signum, frame))) for signum in held
    }
    try:
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
        if received:
            signum, frame = received[0]
            handler = previous[signum]
            if handler is signal.default_int_handler:
                raise KeyboardInterrupt
            if callable(handler):
                handler(signum, frame)
            elif handler == signal.SIG_DFL:
                signal.raise_signal(signum)


def atomic_write(path: str | os.PathLike, write: Callable[[BinaryIO], None]) -> None:
    """Write `path` through `write(f)` into a temporary file beside it, flushed to disk, then
    rename it over `path`: an interrupted or failed write leaves the previous file (or none),
    never a broken one. The folder must exist."""
    path = Path(path)
    if not path.parent.is_dir():
        raise EngineError(f"cannot write {path}: folder {path.parent} does not exist")
    if path.is_dir():
        raise EngineError(f"cannot write {path}: it is a folder")
    with interrupts_deferred():
        try:
            fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
        except OSError as exc:
            raise write_error(path, exc) from None
        try:
            with os.fdopen(fd, "wb") as f:
                write(f)
                f.flush()
                os.fsync(f.fileno())
            os.chmod(tmp, _mode_for(path))  # replacing a file keeps its permissions
            os.replace(tmp, path)
        except BaseException as exc:
            try:
                os.unlink(tmp)
            except FileNotFoundError:
                pass
            if isinstance(exc, OSError):
                raise write_error(path, exc) from None
            raise


def _mode_for(path: Path) -> int:
    """The permissions a file written at `path` gets: those of the file it replaces, else a plain open()'s."""
    try:
        return path.stat().st_mode & 0o7777
    except FileNotFoundError:
        return 0o666 & ~_UMASK


class StagedFiles:
    """Several files written as one (a bake's frames, a conversion's files). Each is written to a
    temporary file beside its target; `commit` moves them all into place at the end. Leaving the
    `with` block without `commit` (an error of any kind, Ctrl-C, a cancel) or `discard` removes the
    temporary files and the folders this made: the targets stay as they were, whether they existed
    or not. A target that cannot be replaced during `commit` puts back the ones moved before it.

        with StagedFiles() as staged:
            staged.write(folder / "a.npz", lambda f: np.savez(f, ...))   # through a file object
            writer(staged.temporary(folder / "b.vdb"))                   # or by a writer that takes a path
            staged.commit()
    """

    def __init__(self):
        self._staged: dict[Path, Path] = {}  # target -> its temporary file
        self._made: list[Path] = []  # folders this made, deepest first
        self.committed = False

    def __enter__(self) -> StagedFiles:
        return self

    def __exit__(self, *exc) -> None:
        if not self.committed:
            self.discard()

    def make_folder(self, folder) -> Path:
        """`folder` and its missing parents, made now and removed again by `discard` when still empty."""
        folder = Path(folder)
        missing = [d for d in (folder, *folder.parents) if not d.exists() and not d.is_symlink()]
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise write_error(folder, exc) from None
        self._made = missing + self._made
        return folder

    def temporary(self, target) -> Path:
        """A new temporary file beside `target` (its folder made when missing), which `commit` moves to
        `target`; the caller writes it."""
        target = Path(target)
        if "\0" in str(target):
            raise EngineError(f"output path {str(target)!r} holds a NUL byte")
        if target in self._staged:
            raise EngineError(f"{target} would be written twice in one run (two inputs of the same name?)")
        if target.is_dir():
            raise EngineError(f"cannot write {target}: it is a folder")
        if not target.parent.is_dir():
            self.make_folder(target.parent)
        try:
            fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
        except OSError as exc:
            raise write_error(target, exc) from None
        os.close(fd)
        self._staged[target] = Path(tmp)
        return Path(tmp)

    def write(self, target, write: Callable[[BinaryIO], None]) -> None:
        """Write the temporary file of `target` through `write(f)`, flushed to disk. Ctrl-C (SIGTERM, SIGHUP)
        waits until the file is written: stopped inside it, a writer such as zipfile's is left half-closed and
        prints a traceback when Python collects it."""
        with interrupts_deferred():
            tmp = self.temporary(target)
            try:
                with open(tmp, "wb") as f:
                    write(f)
                    f.flush()
                    os.fsync(f.fileno())
            except OSError as exc:
                raise write_error(target, exc) from None

    def commit(self) -> None:
        """Move every staged file to its target (replacing what is there); Ctrl-C waits until it is done."""
        done: list[tuple[Path, Path | None]] = []  # (target moved in, backup of what it replaced)
        target = None
        with interrupts_deferred():
            try:
                for target, tmp in self._staged.items():
                    os.chmod(tmp, _mode_for(target))
                    backup = None
                    if target.exists() or target.is_symlink():
                        fd, name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
                        os.close(fd)
                        backup = Path(name)
                        try:
                            os.replace(target, backup)
                        except OSError:
                            os.unlink(backup)
                            raise
                    try:
                        os.replace(tmp, target)
                    except OSError:
                        if backup is not None:
                            os.replace(backup, target)
                        raise
                    done.append((target, backup))
            except OSError as exc:
                for moved, backup in reversed(done):  # put back what the run had replaced
                    try:
                        if backup is not None:
                            os.replace(backup, moved)
                        else:
                            os.unlink(moved)
                    except OSError:
                        pass
                self.discard()
                raise write_error(target, exc) from None
            for _moved, backup in done:
                if backup is not None:
                    try:
                        os.unlink(backup)
                    except OSError:
                        pass
            self._staged.clear()
            self._made.clear()
            self.committed = True

    def discard(self) -> None:
        """Remove every temporary file and the folders this made (those still empty)."""
        for tmp in self._staged.values():
            try:
                os.unlink(tmp)
            except OSError:
                pass
        self._staged.clear()
        for folder in self._made:
            try:
                folder.rmdir()
            except OSError:
                pass
        self._made.clear()


def _probe_folder(folder: Path, what) -> None:
    try:
        fd, probe = tempfile.mkstemp(prefix=".nerf_deform_probe.", suffix=".tmp", dir=folder)
    except OSError as exc:
        raise write_error(what, exc) from None
    os.close(fd)
    os.unlink(probe)


def check_writable(path, folder: bool = False) -> None:
    """EngineError now, before any long work, if `path` cannot be written: a file (its folder
    must exist and take new files) or, with `folder`, a folder to fill (created with its parents
    when missing: the nearest existing one must take new entries)."""
    path = Path(path)
    if "\0" in str(path):
        raise EngineError(f"output path {str(path)!r} holds a NUL byte")
    if folder:
        if path.exists() and not path.is_dir():
            raise EngineError(f"--out {path}: exists and is not a folder")
        existing = path
        while not existing.exists():
            if existing.is_symlink():  # a link to nothing: no folder can be made in its place
                raise EngineError(
                    f"cannot create folder {path}: {existing} is a symbolic link to "
                    f"{os.readlink(existing)}, which does not exist"
                )
            if existing.parent == existing:
                break
            existing = existing.parent
        if not existing.is_dir():
            raise EngineError(f"cannot create folder {path}: {existing} is not a folder")
        _probe_folder(existing, path)
        return
    if path.is_dir():
        raise EngineError(f"cannot write {path}: it is a folder")
    if not path.parent.is_dir():
        raise EngineError(f"cannot write {path}: folder {path.parent} does not exist")
    _probe_folder(path.parent, path)


def remove_stale_temporaries(path) -> int:
    """Delete the temporary files that interrupted atomic writes of `path` left (a process killed
    mid-write cannot clean up). Only call this while no other process writes `path`."""
    path = Path(path)
    removed = 0
    for tmp in path.parent.glob(f".{path.name}.*.tmp"):
        try:
            tmp.unlink()
            removed += 1
        except OSError:
            pass
    return removed


def _try_lock(fd: int) -> bool:
    try:
        import fcntl
    except ImportError:  # Windows
        import msvcrt

        try:
            msvcrt.locking(fd, msvcrt.LK_NBLCK, 1)
            return True
        except OSError:
            return False
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        return True
    except BlockingIOError:
        return False


@contextlib.contextmanager
def folder_lock(folder, name: str = ".lock", holder: str = "another process"):
    """Hold `folder/name` exclusively for the block; EngineError at once if someone else holds it.

    The lock is the kernel's (flock), not the file's existence: a file left by a killed process
    locks nothing. The file is removed when the block ends."""
    lock_path = Path(folder) / name
    while True:
        try:
            fd = os.open(lock_path, os.O_RDWR | os.O_CREAT, 0o666 & ~_UMASK)
        except OSError as exc:
            raise write_error(lock_path, exc) from None
        if not _try_lock(fd):
            try:
                pid = os.read(fd, 32).decode("ascii", "replace").strip()
            finally:
                os.close(fd)
            by = f" (process {pid})" if pid.isdigit() else ""
            raise EngineError(
                f"{folder} is in use by {holder}{by}, which holds {lock_path}; "
                "wait for it to finish or choose another folder"
            )
        # The previous holder may have removed the file between our open and our lock: then we
        # locked a file nobody else will see, so take the one now at the path instead.
        try:
            same = os.fstat(fd).st_ino == os.stat(lock_path).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    try:
        try:
            os.ftruncate(fd, 0)
            os.write(fd, str(os.getpid()).encode("ascii"))  # for the message of whoever is refused
        except OSError:
            pass  # a full disk: the lock holds without it
        yield lock_path
    finally:
        try:
            os.unlink(lock_path)
        except OSError:
            pass
        os.close(fd)
