"""The worker's op registry: what a handler sees of its request (`Job`) and how handlers register (`op`).

Apart from `worker.py` so that the handlers (`ops.py`) and the process loop
import it without importing each other.
"""

from __future__ import annotations

import threading
from typing import TYPE_CHECKING, Callable

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

    def progress(self, fraction: float, message: str = "") -> None:
        """Report progress; raises Cancelled if the client asked to cancel this request."""
        if self.cancel_event.is_set():
            raise Cancelled()
        self.worker.send({"type": "progress", "id": self.id, "fraction": float(fraction), "message": message})


Handler = Callable[[Job], "tuple[dict, dict[str, np.ndarray]] | dict"]
HANDLERS: dict[str, Handler] = {}


def op(name: str) -> Callable[[Handler], Handler]:
    """Register a handler for requests of kind `name`."""

    def register(fn: Handler) -> Handler:
        HANDLERS[name] = fn
        return fn

    return register
