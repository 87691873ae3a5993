"""The engine worker: a process Blender starts on a Python that has torch.

    python -m blender_nerf_deform.engine.service.worker

Reads requests from stdin and answers on stdout in the format of
`protocol.py`; everything else the engine writes (its log records, one plain
line each: logs.py; tqdm; warnings) goes to stderr, which the add-on forwards
to Blender's console and quotes when the worker ends unexpectedly. One request runs at a time;
a cancel for the running request stops it at its next progress report. A side
request (an op registered as a side op, such as `training_preview`) is handed
to the running job instead when that job serves side requests and accepts it
(a training renders its current model between steps): registry.py.

Messages, client → worker:
    {"type": "request", "id": n, "op": "<op>", "params": {...}} + arrays
    {"type": "cancel", "id": n}
    {"type": "shutdown"}
worker → client:
    {"type": "hello", "python": ..., "torch": ..., "cuda": bool, "ops": [...]}   once, at start
    {"type": "fatal", "message": ...}                                         instead of hello, then exit
    {"type": "progress", "id": n, "fraction": f, "message": ...}
    {"type": "result", "id": n, "result": {...}} + arrays
    {"type": "error", "id": n, "kind": "input" | "cancelled" | "missing" | "internal", "message": ..., "traceback": ...}

The worker session (session.py): what Blender gave it (rest cages, surface
embeddings, handle regions) is kept under content keys that the client
chooses; a request names what it uses in params["shared"] = {slot: key} and
carries the arrays of a slot ("<slot>.<name>") only the first time. A key the
worker does not hold (a new worker, or one it dropped) fails the request with
kind "missing" and the slots to send; the client sends them and retries.

Why a process and not a thread in Blender: docs/ARCHITECTURE.md ("Why heavy work runs in a separate process").
"""

from __future__ import annotations

import logging
import os
import platform
import queue
import sys
import threading
import traceback
from typing import TYPE_CHECKING, BinaryIO

from ..errors import EngineError, unexpected_error
from ..logs import log_to_stderr
from .protocol import ProtocolError, read_message, write_message
from .registry import HANDLERS, SIDE_OPS, Cancelled, Handler, Job, Missing

log = logging.getLogger(f"{__package__}.worker")  # also when run as __main__

if TYPE_CHECKING:
    import numpy as np


class Worker:
    def __init__(self, inp: BinaryIO, out: BinaryIO):
        self.inp = inp
        self.out = out
        self._send_lock = threading.Lock()
        self._jobs: queue.Queue[Job | None] = queue.Queue()
        self._current: Job | None = None
        self._pending: dict[int, Job] = {}
        # Guards the running job's side-request queue: the reader's check-and-put against its closing.
        self._side_lock = threading.Lock()

    def send(self, header: dict, arrays: dict[str, np.ndarray] | None = None) -> None:
        with self._send_lock:
            write_message(self.out, header, arrays)

    def _read_requests(self) -> None:
        """Reader thread: queues requests, applies cancels at once, ends on shutdown or EOF."""
        try:
            while (message := read_message(self.inp)) is not None:
                header, arrays = message
                kind = header.get("type")
                if kind == "request":
                    job = Job(self, header["id"], header.get("op"), header.get("params", {}), arrays)
                    self._pending[job.id] = job
                    if not self._hand_to_running(job):
                        self._jobs.put(job)
                elif kind == "cancel":
                    job = self._pending.get(header.get("id"))
                    if job is not None:
                        job.cancel_event.set()
                elif kind == "shutdown":
                    break
        except ProtocolError as exc:
            log.error("worker: %s; stopping", exc)
        finally:
            # Blender went away or asked us to stop: cancel what runs, then end.
            for job in list(self._pending.values()):
                job.cancel_event.set()
            self._jobs.put(None)

    def _hand_to_running(self, job: Job) -> bool:
        """Queue a side request with the running job when it serves side requests and accepts this one."""
        if job.op not in SIDE_OPS:
            return False
        with self._side_lock:
            running = self._current
            if running is None or running.side_requests is None or running.accepts_side is None:
                return False
            try:
                accepted = bool(running.accepts_side(job))
            except Exception:  # a malformed request: its own handler will say what is wrong with it
                accepted = False
            if accepted:
                running.side_requests.put(job)
            return accepted

    def open_side_requests(self, job: Job, accepts) -> None:
        with self._side_lock:
            job.accepts_side = accepts
            job.side_requests = queue.Queue()

    def close_side_requests(self, job: Job) -> None:
        """The job stops serving side requests: the ones it did not answer go to the main queue."""
        with self._side_lock:
            left, job.side_requests, job.accepts_side = job.side_requests, None, None
        while left is not None and not left.empty():
            self._jobs.put(left.get_nowait())

    def run(self, job: Job, handler: Handler | None = None) -> None:
        """Run `job` with `handler` (default: its op's) and send its answer or error with its id."""
        handler = handler or HANDLERS.get(job.op)
        try:
            if job.cancel_event.is_set():
                raise Cancelled()
            if handler is None:
                raise EngineError(f"unknown request {job.op!r}; this worker knows {sorted(HANDLERS)}")
            answer = handler(job)
            result, arrays = answer if isinstance(answer, tuple) else (answer, {})
            self.send({"type": "result", "id": job.id, "result": result}, arrays)
        except Cancelled:
            self.send({"type": "error", "id": job.id, "kind": "cancelled", "message": "cancelled"})
        except Missing as exc:
            self.send({"type": "error", "id": job.id, "kind": "missing", "message": str(exc), "missing": exc.slots})
        except EngineError as exc:
            self.send({"type": "error", "id": job.id, "kind": "input", "message": str(exc)})
        except Exception:  # a bug: keep the worker alive; Blender's report names the log file of its traceback
            self.send(
                {
                    "type": "error",
                    "id": job.id,
                    "kind": "internal",
                    "message": unexpected_error(f"the engine worker's {job.op!r} request"),
                    "traceback": traceback.format_exc(),
                }
            )
        finally:
            self._pending.pop(job.id, None)

    def serve(self) -> int:
        threading.Thread(target=self._read_requests, name="worker-reader", daemon=True).start()
        while (job := self._jobs.get()) is not None:
            with self._side_lock:
                self._current = job
            try:
                self.run(job)
            finally:
                with self._side_lock:
                    self._current = None
        return 0


def _protocol_streams() -> tuple[BinaryIO, BinaryIO]:
    """Keep the real stdout for messages; send everything printed to stderr instead."""
    out = os.fdopen(os.dup(sys.stdout.fileno()), "wb")
    os.dup2(sys.stderr.fileno(), sys.stdout.fileno())
    sys.stdout = sys.stderr
    return sys.stdin.buffer, out


def main() -> int:
    inp, out = _protocol_streams()
    log_to_stderr()  # the engine's log lines: what the add-on forwards to Blender's console
    try:
        import numpy  # noqa: F401

        from ..nerf.model import device_summary  # imports torch
    except ImportError as exc:
        write_message(
            out,
            {
                "type": "fatal",
                "message": f"the worker Python {sys.executable} cannot import {exc.name} ({exc}); "
                "set NeRF Deform's Worker Python preference to a Python 3.11 with the engine's "
                "requirements (torch, numpy, ...) installed",
            },
        )
        return 3
    from . import ops  # noqa: F401  (registers the engine's ops)

    worker = Worker(inp, out)
    worker.send(
        {
            "type": "hello",
            "python": sys.executable,
            "python_version": platform.python_version(),
            **device_summary(),
            "ops": sorted(HANDLERS),
        }
    )
    return worker.serve()


if __name__ == "__main__":
    from ..process_exit import exit_process

    exit_process(main())
