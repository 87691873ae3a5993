"""Client of the engine worker process (docs/ARCHITECTURE.md, "Two halves and a worker process").

Blender never imports torch: heavy work runs in `python -m
<package>.engine.service.worker` on the Python set in the add-on preferences. A reader
thread turns the worker's stdout into messages on a queue; on Blender's main
thread a `bpy.app.timers` function drains it and calls the request's callbacks
(the documented way to bring results from another thread). Blocking callers
that are not on the main thread's event loop (the RenderEngine, `blender -b`)
use `call()`, which waits for its own answer and leaves the others queued.

A worker that crashes or lacks torch fails the pending requests with a clear
message; the next request starts a fresh one. Blender's scene is never touched
from here: callbacks decide what to do with results.

At exit (`shutdown`, run by the add-on's unregister and by an `atexit` hook)
the worker is stopped, its reader threads end, and every request's callbacks
are let go. The reader threads are daemons that hold the client: left running
at exit, they would keep the queued callbacks (the preview's, whose module
globals hold `bpy`) alive forever, and the bpy module of Blender 4.2 and 4.5
runs Blender's own exit only when the `bpy` module is freed: a process with a
preview solve still queued segfaulted at exit in 4.2 (exit 139) and hung there
in 4.5. Blender 5.x exits either way.

The worker session (engine/service/requests.py): a request may name shared content, `shared =
{slot: (content key, loader)}`. The client remembers what it gave the running
worker and calls a slot's loader (and sends its arrays) only for a key that
worker has not been given; a worker that answers "missing" (it dropped the
content) gets it again with the same request. Every message's size is counted
(`bytes_sent`, `sent`: (op, bytes) of the recent requests).
"""

from __future__ import annotations

import collections
import itertools
import os
import queue
import shutil
import subprocess
import sys
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ...engine.service.protocol import ProtocolError, read_message, write_message
from ..data.guards import call_guarded

# The extension's package folder and its name (`blender_nerf_deform`, whatever
# `bl_ext.<repo>.` prefix Blender gives the module); the worker imports the
# engine from the folder's parent.
PACKAGE_DIR = Path(__file__).resolve().parents[2]  # addon/worker/client.py
WORKER_MODULE = f"{PACKAGE_DIR.name}.engine.service.worker"
# How long a starting worker may take to answer (importing torch, compiling kernels on a busy
# machine take minutes); $NERF_DEFORM_WORKER_START_TIMEOUT (seconds) overrides it.
START_TIMEOUT_S = 300.0
_STDERR_LINES = 40


class WorkerError(Exception):
    """The request failed; the message is written for Blender's report."""

    def __init__(self, message: str, kind: str = "internal", details: str = ""):
        super().__init__(message)
        self.kind = kind
        self.details = details


@dataclass
class _Request:
    id: int
    on_done: Callable[[dict, dict], None] | None = None
    on_error: Callable[[WorkerError], None] | None = None
    on_progress: Callable[[float, str], None] | None = None
    inbox: queue.Queue = field(default_factory=queue.Queue)
    blocking: bool = False
    proc: subprocess.Popen | None = None  # the worker it was sent to
    send: tuple = ()  # (op, params, arrays, shared): what to send again when the worker misses shared content
    resent: bool = False


def worker_environment(inherit_pythonpath: bool = True) -> tuple[dict, str]:
    """(environment, working folder) of an engine process started for the worker: the engine's package
    importable, numba's kernel cache in the user folder (so that Set Up Worker's `compile` fills the
    cache the worker reads), and no bytecode written: an installed extension's own folder is Blender's
    to replace, not ours to write. The engine's few modules compile at each start, which is cheap; torch
    and the other packages load the bytecode their install wrote. (Redirecting all bytecode to the user
    folder with PYTHONPYCACHEPREFIX would hide that bytecode too: where PYTHONDONTWRITEBYTECODE is set, as
    in containers, every start would compile torch again, which costs more than the rest of the start.)"""
    env = dict(os.environ)
    env.pop("PYTHONHOME", None)
    inherited = env.get("PYTHONPATH", "") if inherit_pythonpath else ""
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(PACKAGE_DIR.parent), inherited) if p)
    env["PYTHONUNBUFFERED"] = "1"
    env["PYTHONDONTWRITEBYTECODE"] = "1"
    work = worker_directory()
    env.setdefault("NUMBA_CACHE_DIR", os.path.join(work, "numba_cache"))
    return env, work


def worker_directory() -> str:
    """The worker's working folder: the extension's user folder (never the extension's own
    folder, which Blender may replace on update), or a temporary one when not an extension."""
    import tempfile

    try:
        import bpy

        from ..data.paths import ADDON_PACKAGE  # imports bpy: this module also runs without it

        return bpy.utils.extension_path_user(ADDON_PACKAGE, path="worker", create=True)
    except (ImportError, ValueError, AttributeError):
        path = os.path.join(tempfile.gettempdir(), "nerf_deform_worker")
        os.makedirs(path, exist_ok=True)
        return path


def python_has_torch(python: str) -> bool:
    """Whether `python` can import torch (asked without importing it: fast)."""
    try:
        proc = subprocess.run(
            [python, "-c", "import importlib.util, sys; sys.exit(importlib.util.find_spec('torch') is None)"],
            capture_output=True,
            timeout=30,
        )
    except (OSError, subprocess.TimeoutExpired):
        return False
    return proc.returncode == 0


def candidate_pythons(preferred: str = "") -> list[str]:
    """Where to look for a worker Python, best first: the preference, $NERF_DEFORM_PYTHON,
    the .venv of a source checkout the add-on runs from, python3.11 and python3 on PATH."""
    found = [preferred, os.environ.get("NERF_DEFORM_PYTHON", "")]
    found.append(str(PACKAGE_DIR.parent / ".venv" / "bin" / "python"))
    found += [shutil.which(name) or "" for name in ("python3.11", "python3")]
    unique = []
    for python in found:
        if python and python not in unique and Path(python).is_file():
            unique.append(python)
    return unique


def detect_python(preferred: str = "") -> str | None:
    """The preferred Python if set, else the first candidate that has torch."""
    if preferred:
        return preferred
    return next((python for python in candidate_pythons() if python_has_torch(python)), None)


class WorkerClient:
    """One worker process and its requests. Thread-safe for submitting; callbacks run on the draining thread."""

    def __init__(self, python: str):
        self.python = python
        self.hello: dict | None = None
        self._proc: subprocess.Popen | None = None
        self._requests: dict[int, _Request] = {}
        self._ids = itertools.count(1)
        self._lock = threading.RLock()
        self._main_inbox: queue.Queue = queue.Queue()
        self._readers: list[threading.Thread] = []  # the current worker's stdout and stderr threads
        self._stderr_tail: collections.deque[str] = collections.deque(maxlen=_STDERR_LINES)
        self._given: set[tuple[str, str]] = set()  # (slot, key) the running worker holds
        self.bytes_sent = 0
        self.sent: collections.deque[tuple[str, int]] = collections.deque(maxlen=256)

    # -- process lifecycle -------------------------------------------------

    @property
    def running(self) -> bool:
        return self._proc is not None and self._proc.poll() is None

    def ensure_started(self) -> dict:
        """Start the worker if it is not running; returns its hello (Python, torch, CUDA)."""
        with self._lock:
            if self.running and self.hello is not None:
                return self.hello
            self._start()
            return self.hello

    def _start(self) -> None:
        if not self.python:
            raise WorkerError(
                "no worker Python is set: set NeRF Deform's Worker Python preference to a Python 3.11 with torch",
                "setup",
            )
        if not Path(self.python).is_file():
            raise WorkerError(
                f"worker Python {self.python} does not exist: fix NeRF Deform's Worker Python preference", "setup"
            )
        env, work = worker_environment()
        self._stderr_tail.clear()
        self._given.clear()  # a new worker holds nothing yet
        try:
            proc = subprocess.Popen(
                [self.python, "-m", WORKER_MODULE],
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                env=env,
                cwd=work,
            )
        except OSError as exc:
            raise WorkerError(f"cannot start worker Python {self.python}: {exc}", "setup") from None
        self._proc = proc
        stderr_pump = threading.Thread(target=self._pump_stderr, args=(proc,), name="nerf-worker-stderr", daemon=True)
        stderr_pump.start()
        first: queue.Queue = queue.Queue()
        stdout_pump = threading.Thread(
            target=self._pump_stdout, args=(proc, first), name="nerf-worker-stdout", daemon=True
        )
        stdout_pump.start()
        self._readers = [stderr_pump, stdout_pump]
        timeout = START_TIMEOUT_S
        try:
            timeout = float(os.environ.get("NERF_DEFORM_WORKER_START_TIMEOUT") or timeout)
        except ValueError:
            pass  # not a number: the default
        if not timeout > 0:  # zero, negative or NaN: the default
            timeout = START_TIMEOUT_S
        timeout = min(timeout, 1e6)
        try:
            header, _ = first.get(timeout=timeout)
        except queue.Empty:
            self._kill()
            stderr_pump.join(timeout=1.0)  # the last lines it wrote reach the tail
            tail = "\n".join(self._stderr_tail).strip()
            raise WorkerError(
                f"the NeRF worker ({self.python} -m {WORKER_MODULE}, in {work}) did not answer within {timeout:g} s "
                "of starting and was stopped. It may only have been slow (importing torch or compiling kernels on a "
                "busy machine): try again, or give it longer with the environment variable "
                "NERF_DEFORM_WORKER_START_TIMEOUT=<seconds>. "
                + (
                    f"Its last output:\n{tail}"
                    if tail
                    else "It wrote nothing (its output goes to Blender's console, prefixed [nerf worker])."
                ),
                "setup",
            ) from None
        if header.get("type") == "fatal":
            self._kill()
            raise WorkerError(header["message"], "setup")
        if header.get("type") != "hello":
            self._kill()
            stderr_pump.join(timeout=1.0)  # its last lines (why it ended) reach the report
            raise WorkerError(f"worker Python {self.python} failed to start: {self._exit_report()}", "setup")
        self.hello = header

    def _kill(self) -> None:
        if self._proc is not None and self._proc.poll() is None:
            self._proc.kill()
            self._proc.wait()

    def stop(self) -> None:
        """Ask the worker to finish, then make sure it is gone."""
        with self._lock:
            proc, self._proc = self._proc, None
            pending = list(self._requests.values())
            self._requests.clear()
        for request in pending:
            self._deliver(
                request,
                (
                    {"type": "error", "id": request.id, "kind": "cancelled", "message": "the NeRF worker was stopped"},
                    {},
                ),
            )
        with self._lock:
            if proc is None:
                return
            try:
                write_message(proc.stdin, {"type": "shutdown"})
                proc.stdin.close()
                proc.wait(timeout=5)
            except (OSError, subprocess.TimeoutExpired, ValueError):
                proc.kill()
                proc.wait()
            readers, self._readers = self._readers, []
        # The worker is gone, so its pipes end and so do the threads reading them (outside the
        # lock: the stdout reader takes it on its way out).
        for thread in readers:
            if thread is not threading.current_thread():
                thread.join(timeout=5)

    def forget_pending(self) -> None:
        """Drop every request and every queued answer without calling back (Blender is quitting
        or the add-on is disabled: nothing will drain them, and they hold the callers' objects)."""
        with self._lock:
            self._requests.clear()
        while True:
            try:
                self._main_inbox.get_nowait()
            except queue.Empty:
                return

    def _exit_report(self, proc: subprocess.Popen | None = None) -> str:
        """How the worker `proc` (default: the current one) ended, with its last output."""
        proc = proc or self._proc
        code = proc.poll() if proc is not None else None
        tail = "\n".join(self._stderr_tail).strip()
        what = f"exited with code {code}" if code is not None else "stopped answering"
        return f"{what}" + (f"; its last output:\n{tail}" if tail else "")

    # -- reader threads ------------------------------------------------------

    def _pump_stderr(self, proc: subprocess.Popen) -> None:
        for raw in proc.stderr:
            line = raw.decode(errors="replace").rstrip()
            self._stderr_tail.append(line)
            print(f"[nerf worker] {line}", file=sys.stderr)

    def _pump_stdout(self, proc: subprocess.Popen, first: queue.Queue) -> None:
        """Route each message to its request's inbox; on exit, fail what is pending."""
        got_first = False
        try:
            while (message := read_message(proc.stdout)) is not None:
                if not got_first:
                    got_first = True
                    first.put(message)
                    continue
                self._route(message)
        except (ProtocolError, OSError, ValueError) as exc:
            self._stderr_tail.append(f"(protocol: {exc})")
        proc.wait()
        if not got_first:
            first.put(({"type": "exited"}, {}))
        # Fail exactly the requests this process had; a restarted worker's are not ours.
        with self._lock:
            pending = [r for r in self._requests.values() if r.proc is proc]
            for request in pending:
                del self._requests[request.id]
        if pending:
            message = f"the NeRF worker {self._exit_report(proc)}"
            for request in pending:
                self._deliver(request, ({"type": "error", "id": request.id, "kind": "crashed", "message": message}, {}))

    def _route(self, message: tuple[dict, dict]) -> None:
        header, _ = message
        with self._lock:
            request = self._requests.get(header.get("id"))
            if request is not None and header.get("type") in ("result", "error"):
                del self._requests[request.id]
        if request is not None:
            self._deliver(request, message)

    def _deliver(self, request: _Request, message: tuple[dict, dict]) -> None:
        if request.blocking:
            request.inbox.put(message)
        else:
            self._main_inbox.put((request, message))

    # -- requests --------------------------------------------------------------

    def _send_request(
        self, request: _Request, op: str, params: dict, arrays: dict[str, np.ndarray] | None, shared: dict | None = None
    ) -> None:
        request.send = (op, params, arrays, shared)
        with self._lock:
            self.ensure_started()
            request.proc = self._proc
            params, arrays, given = self._with_shared(params, arrays, shared)
            self._requests[request.id] = request
            try:
                n = write_message(
                    self._proc.stdin, {"type": "request", "id": request.id, "op": op, "params": params}, arrays
                )
            except (OSError, ValueError):
                del self._requests[request.id]
                raise WorkerError(f"the NeRF worker {self._exit_report()}", "crashed") from None
            self._given |= given
            self.bytes_sent += n
            self.sent.append((op, n))

    def _with_shared(self, params: dict, arrays: dict | None, shared: dict | None) -> tuple[dict, dict, set]:
        """The request's params naming its shared content, its arrays plus the content the worker lacks."""
        if not shared:
            return params, arrays, set()
        params = {**params, "shared": {slot: key for slot, (key, _load) in shared.items()}}
        arrays, given = dict(arrays or {}), set()
        for slot, (key, load) in shared.items():
            if (slot, key) not in self._given:
                arrays.update({f"{slot}.{name}": a for name, a in load().items()})
                given.add((slot, key))
        return params, arrays, given

    def _resend_if_missing(self, request: _Request, header: dict) -> bool:
        """Send a request again, with its shared content, when the worker did not hold it (once)."""
        if header.get("type") != "error" or header.get("kind") != "missing" or request.resent or not request.send:
            return False
        op, params, arrays, shared = request.send
        missing = set(header.get("missing") or (shared or {}))
        with self._lock:
            self._given -= {(slot, key) for slot, (key, _load) in (shared or {}).items() if slot in missing}
        request.resent = True
        self._send_request(request, op, params, arrays, shared)
        return True

    def submit(
        self,
        op: str,
        params: dict | None = None,
        arrays: dict[str, np.ndarray] | None = None,
        *,
        on_done: Callable[[dict, dict], None] | None = None,
        on_error: Callable[[WorkerError], None] | None = None,
        on_progress: Callable[[float, str], None] | None = None,
        shared: dict | None = None,
    ) -> int:
        """Send a request without waiting; callbacks run when `drain()` runs (a Blender timer)."""
        request = _Request(next(self._ids), on_done, on_error, on_progress)
        self._send_request(request, op, params or {}, arrays, shared)
        return request.id

    def cancel(self, request_id: int) -> None:
        with self._lock:
            if request_id in self._requests and self.running:
                try:
                    write_message(self._proc.stdin, {"type": "cancel", "id": request_id})
                except (OSError, ValueError):
                    pass

    def in_flight(self, op: str) -> list[dict]:
        """The params of this client's requests of `op` that the worker has not answered yet
        (Preview Training asks which trainings run)."""
        with self._lock:
            return [r.send[1] for r in self._requests.values() if r.send and r.send[0] == op]

    @property
    def busy(self) -> bool:
        return bool(self._requests) or not self._main_inbox.empty()

    def drain(self) -> int:
        """Run the callbacks of messages that arrived; call on Blender's main thread. Returns how many."""
        handled = 0
        while True:
            try:
                request, (header, arrays) = self._main_inbox.get_nowait()
            except queue.Empty:
                return handled
            handled += 1
            kind = header.get("type")
            try:
                if self._resend_if_missing(request, header):
                    continue
            except Exception as error:  # the content could not be loaded again (or the worker died): fail this request
                header = {"type": "error", "kind": getattr(error, "kind", "input"), "message": str(error)}
            # Guarded: a callback's error nobody foresaw is said once, and the next messages still run.
            where = "NeRF Deform: an answer of the worker"
            if kind == "progress" and request.on_progress:
                call_guarded(where, request.on_progress, header["fraction"], header.get("message", ""))
            elif kind == "result" and request.on_done:
                call_guarded(where, request.on_done, header["result"], arrays)
            elif kind == "error" and request.on_error:
                call_guarded(where, request.on_error, _error_from(header))

    def call(
        self,
        op: str,
        params: dict | None = None,
        arrays: dict[str, np.ndarray] | None = None,
        *,
        on_progress: Callable[[float, str], None] | None = None,
        should_cancel: Callable[[], bool] | None = None,
        poll_s: float = 0.05,
        shared: dict | None = None,
    ) -> tuple[dict, dict[str, np.ndarray]]:
        """Send a request and wait for its answer (for renders and scripts).

        `should_cancel` is polled while waiting (RenderEngine.test_break); when it
        returns True the request is cancelled and WorkerError(kind="cancelled") raised.
        """
        request = _Request(next(self._ids), blocking=True)
        self._send_request(request, op, params or {}, arrays, shared)
        cancel_sent = False
        while True:
            try:
                header, out_arrays = request.inbox.get(timeout=poll_s)
            except queue.Empty:
                if should_cancel is not None and not cancel_sent and should_cancel():
                    self.cancel(request.id)
                    cancel_sent = True
                continue
            kind = header.get("type")
            if kind == "progress":
                if on_progress:
                    on_progress(header["fraction"], header.get("message", ""))
            elif kind == "result":
                return header["result"], out_arrays
            elif kind == "error":
                if self._resend_if_missing(request, header):
                    continue
                raise _error_from(header)


def _error_from(header: dict) -> WorkerError:
    return WorkerError(
        header.get("message", "unknown error"), header.get("kind", "internal"), header.get("traceback", "")
    )


# -- the add-on's one worker, drained by a Blender timer ---------------------------

_client: WorkerClient | None = None
_DRAIN_BUSY_S = 0.05
_DRAIN_IDLE_S = 0.25


def get_client(python: str) -> WorkerClient:
    """The shared worker for this Blender session, restarted on another Python."""
    global _client
    if _client is None or _client.python != python:
        if _client is not None:
            _client.stop()
        _client = WorkerClient(python)
    _ensure_timer()
    return _client


def active_client() -> WorkerClient | None:
    """The shared worker's client if one was made (starts nothing: for polls and panels)."""
    return _client


def detach_client() -> WorkerClient | None:
    """Take the shared worker out of the add-on without stopping it (`shutdown` then leaves it
    running); `adopt_client` hands it back. The test suite keeps one worker per test module across
    its register/unregister cycles this way, instead of a torch import and a kernel load per test."""
    global _client
    client, _client = _client, None
    return client


def adopt_client(client: WorkerClient | None) -> None:
    """Make `client` (from `detach_client`) the shared worker again; a stopped one restarts on demand."""
    global _client
    if client is None or client is _client:
        return
    if _client is not None:
        _client.stop()
    _client = client
    _ensure_timer()


def _drain_timer() -> float | None:
    if _client is None:
        return None
    call_guarded("NeRF Deform: the worker's answers", _client.drain)
    # Keeps running while a client exists: answers can arrive at any time.
    return _DRAIN_BUSY_S if _client.busy else _DRAIN_IDLE_S


def _ensure_timer() -> None:
    import bpy

    if not bpy.app.timers.is_registered(_drain_timer):
        bpy.app.timers.register(_drain_timer, first_interval=_DRAIN_BUSY_S, persistent=True)


def shutdown() -> None:
    """Stop the worker and let go of every callback (add-on disabled, Blender quitting: the
    module docstring says why nothing may outlive this)."""
    global _client
    import bpy

    if bpy.app.timers.is_registered(_drain_timer):
        bpy.app.timers.unregister(_drain_timer)
    client, _client = _client, None
    if client is not None:
        client.stop()
        client.forget_pending()
