"""The worker's op registry: what a handler sees of its request (`Job`) and how handlers register (`op`).

Apart from `worker.py` so that the handlers (`ops.py`) and the process loop
import it without importing each other.

Side requests: the worker runs one request at a time, but a long one (training) can
answer small requests while it runs. An op registered with `side=True` (SIDE_OPS) is a
side op: when the running job opened `serving_side_requests` and accepts it, the worker's
reader hands it to that job's queue instead of the main one; the job answers it between
its own steps (`serve_side_requests`), and what it did not answer when the block ends goes
to the main queue, where the op's own handler runs it.
"""

from __future__ import annotations

import contextlib
import queue
import threading
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING

from ..errors import EngineError

if TYPE_CHECKING:
    import numpy as np


class Missing(EngineError):
    """A request named session content (by key) that this worker does not hold: the client sends it again."""

    def __init__(self, slots: list[str]):
        super().__init__(f"the worker does not hold {', '.join(slots)}; send it with the request")
        self.slots = slots


class Cancelled(Exception):
    """The client cancelled the running request."""


class Job:
    """What an op handler sees of its request: params, arrays, progress and cancellation."""

    def __init__(self, worker, request_id: int, op: str, params: dict, arrays: dict[str, np.ndarray]):
        self.worker = worker  # the Worker that sends this job's progress
        self.id = request_id
        self.op = op
        self.params = params
        self.arrays = arrays
        self.cancel_event = threading.Event()
        self.side_requests: queue.Queue[Job] | None = None  # open while the job serves side requests
        self.accepts_side: Callable[[Job], bool] | None = None

    @contextlib.contextmanager
    def serving_side_requests(self, accepts: Callable[[Job], bool]) -> Iterator[None]:
        """While the block runs, the worker hands this job the side requests that `accepts(side_job)`
        takes; those still queued when it ends go to the worker's main queue."""
        self.worker.open_side_requests(self, accepts)
        try:
            yield
        finally:
            self.worker.close_side_requests(self)

    def serve_side_requests(self, handler: Handler) -> int:
        """Answer the side requests queued so far with `handler(side_job)`; each answer (or error)
        goes out with the side request's id. Returns how many were answered."""
        served = 0
        while self.side_requests is not None:
            try:
                side = self.side_requests.get_nowait()
            except queue.Empty:
                break
            self.worker.run(side, handler)
            served += 1
        return served

    def progress(self, fraction: float, message: str = "") -> None:
        """Report progress; raises Cancelled if the client asked to cancel this request."""
        if self.cancel_event.is_set():
            raise Cancelled()
        self.worker.send({"type": "progress", "id": self.id, "fraction": float(fraction), "message": message})


Handler = Callable[[Job], "tuple[dict, dict[str, np.ndarray]] | dict"]
HANDLERS: dict[str, Handler] = {}
SIDE_OPS: set[str] = set()


def op(name: str, side: bool = False) -> Callable[[Handler], Handler]:
    """Register a handler for requests of kind `name`; `side`: a side op (see the module docstring)."""

    def register(fn: Handler) -> Handler:
        HANDLERS[str(name)] = fn  # the op's plain name (requests.Op is a StrEnum), as the wire spells it
        if side:
            SIDE_OPS.add(str(name))
        return fn

    return register
