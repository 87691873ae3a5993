"""Operators whose work runs in the engine worker.

One operator, two ways to run, as Blender's own long operators offer:
- `execute` (scripts, `bpy.ops` from Python, `blender -b`, tests) sends the
  request and waits for the answer; the status is printed.
- `invoke` (a button in the UI) sends it and returns at once; a modal timer
  shows progress in the status bar and the window's progress cursor, Esc
  cancels, and the result is applied on Blender's main thread.
Either way the scene changes only in `apply`, after the worker answered, so a
failed or cancelled job leaves the scene as it was.

A chain of requests (Import Photos: prepare, then train): `apply` may return
the next `WorkerRequest` instead of Blender's result set; the operator then
sends it, with the same progress, status bar (each request's `stage` names it,
"1/2 cameras: ...") and Esc, and `execute` runs the whole chain blocking. Esc
cancels the request running; one that finished anyway (its cancel came too
late) is applied, but no next request is sent.
"""

from __future__ import annotations

from typing import NamedTuple

import bpy

from ..data.paths import worker_python
from .client import WorkerClient, WorkerError, detect_python, get_client

_detected: dict[str, str | None] = {}


def worker(context) -> WorkerClient:
    """The shared worker, on the preferred Python or the first one found with torch (looked for
    once per preference value: detection starts interpreters)."""
    preferred = worker_python(context)
    preferred = bpy.path.abspath(preferred) if preferred else ""
    if _detected.get(preferred) is None:
        _detected[preferred] = detect_python(preferred)
    python = _detected[preferred]
    if python is None:
        raise WorkerError(
            "no Python with torch found: set NeRF Deform's Worker Python preference "
            "(Edit > Preferences > Add-ons > NeRF Deform), see the README",
            "setup",
        )
    return get_client(python)


class WorkerRequest(NamedTuple):
    """One request of an operator; `stage` names it in the progress and the status bar (a chain's step)."""

    op: str
    params: dict
    arrays: dict | None = None
    stage: str = ""
    shared: dict | None = None  # worker-session content the request names (client.py)


def _as_request(request) -> WorkerRequest:
    return request if isinstance(request, WorkerRequest) else WorkerRequest(*request)


class WorkerOperator:
    """Mixin: define `request(context) -> (op, params, arrays)` (or a WorkerRequest) and
    `apply(context, result, arrays)` -> Blender's result set, or the next WorkerRequest of a chain.
    `self.current_request` is the request being answered (a chain's `apply` reads its op)."""

    _job_id: int | None = None
    _timer = None
    current_request = None  # the WorkerRequest answered now (no annotation: Blender reads those as properties)

    def request(self, context):
        raise NotImplementedError

    def apply(self, context, result: dict, arrays: dict) -> set[str]:
        raise NotImplementedError

    def abandon(self, context) -> None:
        """A chain stopped before its end (Esc between two requests): undo what its stages left."""

    def _label(self) -> str:
        """What progress and errors start with: the operator, and the stage of a chain."""
        stage = self.current_request.stage if self.current_request is not None else ""
        return f"{self.bl_label}: {stage}" if stage else self.bl_label

    def _fail(self, error: Exception) -> set[str]:
        self.report({"ERROR"}, f"{self._label()}: {error}")
        return {"CANCELLED"}

    def execute(self, context):
        try:
            request = _as_request(self.request(context))
            client = worker(context)
        except (WorkerError, ValueError) as error:
            return self._fail(error)
        while True:
            self.current_request = request
            label = self._label()
            try:
                result, out = client.call(
                    request.op,
                    request.params,
                    request.arrays,
                    shared=request.shared,
                    on_progress=lambda f, msg, label=label: print(f"{label}: {100 * f:5.1f}% {msg}"),
                )
            except (WorkerError, ValueError) as error:
                return self._fail(error)
            answer = self.apply(context, result, out)
            if not isinstance(answer, WorkerRequest):
                return answer
            request = answer

    def _submit(self, request: WorkerRequest) -> None:
        self.current_request = request
        self._state = {"done": None, "progress": 0.0, "message": ""}
        self._job_id = self._client.submit(
            request.op,
            request.params,
            request.arrays,
            on_done=lambda result, out: self._state.update(done=("ok", result, out)),
            on_error=lambda error: self._state.update(done=("error", error, None)),
            on_progress=lambda f, msg: self._state.update(progress=f, message=msg),
            shared=request.shared,
        )

    def invoke(self, context, event):
        try:
            request = _as_request(self.request(context))
            self._client = worker(context)
            self._cancel_asked = False
            self._submit(request)
        except (WorkerError, ValueError) as error:
            return self._fail(error)
        wm = context.window_manager
        self._timer = wm.event_timer_add(0.1, window=context.window)
        wm.progress_begin(0, 100)
        wm.modal_handler_add(self)
        return {"RUNNING_MODAL"}

    def _finish(self, context):
        wm = context.window_manager
        if self._timer is not None:
            wm.event_timer_remove(self._timer)
            self._timer = None
        wm.progress_end()
        if context.workspace is not None:
            context.workspace.status_text_set(None)

    def clean_up_after_error(self, context) -> None:
        """What an error nobody foresaw leaves to undo (data/guards.py calls it): the modal timer and the
        status text, the job still running in the worker, and what the chain's stages left (`abandon`)."""
        if self._timer is not None:
            self._finish(context)
        client = getattr(self, "_client", None)
        if client is not None and self._job_id is not None and getattr(self, "_state", {}).get("done") is None:
            client.cancel(self._job_id)
        self.abandon(context)

    def modal(self, context, event):
        client = self._client
        if event.type == "ESC":
            self._cancel_asked = True
            client.cancel(self._job_id)
        if event.type != "TIMER":
            return {"PASS_THROUGH"}
        client.drain()
        state = self._state
        if state["done"] is None:
            context.window_manager.progress_update(int(100 * state["progress"]))
            context.workspace.status_text_set(
                f"{self._label()}: {100 * state['progress']:.0f}% {state['message']} (Esc to cancel)"
            )
            return {"RUNNING_MODAL"}
        kind, payload, out = state["done"]
        if kind == "error":
            self._finish(context)
            return self._fail(payload)
        answer = self.apply(context, payload, out)  # an error here: clean_up_after_error (data/guards.py)
        if not isinstance(answer, WorkerRequest):
            self._finish(context)
            return answer
        if self._cancel_asked:  # the stage ended before the cancel reached it: go no further
            self._finish(context)
            self.abandon(context)
            self.report(
                {"WARNING"}, f"{self._label()}: cancelled after this stage; {answer.stage or answer.op} not started"
            )
            return {"CANCELLED"}
        try:
            self._submit(answer)
        except (WorkerError, ValueError) as error:
            self._finish(context)
            return self._fail(error)
        return {"RUNNING_MODAL"}
