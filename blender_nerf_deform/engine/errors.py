"""Errors the engine raises for bad input: one clear line naming what is wrong.

The command line prints `error: <message>` and exits non-zero; the worker
process forwards the message to Blender's report. Anything else that escapes
is a bug: `unexpected_error` saves its traceback to a log file and gives the one
line to show instead, naming that file (every boundary, the command line's, a
tool's, the worker's and the add-on's, ends that way).
"""

from __future__ import annotations

import itertools
import os
import tempfile
import time
import traceback

# Where tracebacks of unexpected errors go: $NERF_DEFORM_LOG_DIR, else this folder under the system's
# temporary folder.
LOG_FOLDER_NAME = "blender_nerf_deform_logs"
_log_numbers = itertools.count(1)


class EngineError(Exception):
    """Bad input or an impossible request; the message names the file, key or value at fault."""


def log_folder() -> str:
    return os.environ.get("NERF_DEFORM_LOG_DIR") or os.path.join(tempfile.gettempdir(), LOG_FOLDER_NAME)


def unexpected_error(where: str, error: BaseException | None = None) -> str:
    """The one line that reports `error` (default: the exception being handled), a bug, at `where`
    (a command, an operator, a handler): its type and message, and the log file that now holds its
    traceback (or why none could be written)."""
    if error is None:
        import sys

        error = sys.exc_info()[1]
    text = "".join(traceback.format_exception(type(error), error, error.__traceback__)) if error is not None else ""
    folder = log_folder()
    name = f"error-{time.strftime('%Y%m%d-%H%M%S')}-{os.getpid()}-{next(_log_numbers)}.log"
    try:
        os.makedirs(folder, exist_ok=True)
        path = os.path.join(folder, name)
        with open(path, "w", encoding="utf-8") as f:
            f.write(f"{where}\n{text}")
        saved = f"its traceback is in {path}"
    except OSError as exc:
        saved = (
            f"its traceback could not be saved in {folder} "
            f"({exc.strerror or exc}; set NERF_DEFORM_LOG_DIR to a writable folder)"
        )
    try:
        summary = f"{type(error).__name__}: {error}" if error is not None else "unknown error"
    except Exception:  # an exception whose own text fails: its type must still be said
        summary = f"{type(error).__name__}: <its message could not be read>"
    summary = " ".join(summary.split())[:300]  # one line, whatever the exception's text held
    return f"{where}: unexpected error ({summary}); {saved}: please report it"


class Terminated(KeyboardInterrupt):
    """SIGTERM or SIGHUP (a job killed by its scheduler, a closed terminal), raised where Python is, so
    clean-up runs (`with`, `finally`: staged files removed, checkpoints finished) as for Ctrl-C; without
    it the process ends at once and leaves its temporary files and the folders it made."""

    def __init__(self, signum: int):
        import signal

        super().__init__(signal.Signals(signum).name)
        self.signum = signum


def _raise_terminated(signum, frame):
    raise Terminated(signum)


def _terminate_as_exception() -> None:
    """SIGTERM and SIGHUP raise Terminated, where they would end the process untidily (their default;
    a handler someone installed is kept). Only the main thread can set handlers."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        return
    for name in ("SIGTERM", "SIGHUP"):
        signum = getattr(signal, name, None)  # no SIGHUP on Windows
        if signum is not None and signal.getsignal(signum) == signal.SIG_DFL:
            signal.signal(signum, _raise_terminated)


def run_command(where: str, body) -> int:
    """A command's exit status, running `body()` (its own status; None is 0): bad input (EngineError) is
    `error: <message>` on stderr and 2, Ctrl-C `interrupted` and 130 (SIGTERM, SIGHUP: `terminated` and
    128 + the signal), an error nobody foresaw one `error:` line naming the log of its traceback and 1.
    The body's own clean-up (with, finally) has run by then."""
    import sys

    _terminate_as_exception()
    try:
        return body() or 0
    except EngineError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except Terminated as exc:
        print(f"terminated by {exc}", file=sys.stderr)
        return 128 + exc.signum
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except Exception:
        print(f"error: {unexpected_error(where)}", file=sys.stderr)
        return 1
