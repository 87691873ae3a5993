"""Operators whose work runs in the engine worker.

One operator, two ways to run, as Blender's own long operators offer:
- `execute` (scripts, `bpy.ops` from Python, `blender -b`, tests) sends the
  request and waits for the answer; the status is printed.
- `invoke` (a button in the UI) sends it and returns at once; a modal timer
  shows progress in the status bar and the window's progress cursor, Esc
  cancels, and the result is applied on Blender's main thread.
Either way the scene changes only in `apply`, after the worker answered, so a
failed or cancelled job leaves the scene as it was.
"""

from __future__ import annotations

import bpy

from . import preferences
from .worker_client import WorkerClient, WorkerError, detect_python, get_client


_detected: dict[str, str | None] = {}


def worker(context) -> WorkerClient:
    """The shared worker, on the preferred Python or the first one found with torch (looked for
    once per preference value: detection starts interpreters)."""
    preferred = preferences.worker_python(context)
    preferred = bpy.path.abspath(preferred) if preferred else ""
    if _detected.get(preferred) is None:
        _detected[preferred] = detect_python(preferred)
    python = _detected[preferred]
    if python is None:
        raise WorkerError(
            "no Python with torch found: set NeRF Deform's Worker Python preference "
            "(Edit > Preferences > Add-ons > NeRF Deform), see the README", "setup"
        )
    return get_client(python)


class WorkerOperator:
    """Mixin: define `request(context) -> (op, params, arrays)` and `apply(context, result, arrays)`."""

    _job_id: int | None = None
    _timer = None

    def request(self, context):
        raise NotImplementedError

    def apply(self, context, result: dict, arrays: dict) -> set[str]:
        raise NotImplementedError

    def _fail(self, error: Exception) -> set[str]:
        self.report({"ERROR"}, f"{self.bl_label}: {error}")
        return {"CANCELLED"}

    def execute(self, context):
        try:
            op, params, arrays = self.request(context)
            result, out = worker(context).call(
                op, params, arrays, on_progress=lambda f, msg: print(f"{self.bl_label}: {100 * f:5.1f}% {msg}")
            )
        except (WorkerError, ValueError) as error:
            return self._fail(error)
        return self.apply(context, result, out)

    def invoke(self, context, event):
        try:
            op, params, arrays = self.request(context)
            client = self._client = worker(context)
            self._state = {"done": None, "progress": 0.0, "message": ""}
            self._job_id = client.submit(
                op,
                params,
                arrays,
                on_done=lambda result, out: self._state.update(done=("ok", result, out)),
                on_error=lambda error: self._state.update(done=("error", error, None)),
                on_progress=lambda f, msg: self._state.update(progress=f, message=msg),
            )
        except (WorkerError, ValueError) as error:
            return self._fail(error)
        wm = context.window_manager
        self._timer = wm.event_timer_add(0.1, window=context.window)
        wm.progress_begin(0, 100)
        wm.modal_handler_add(self)
        return {"RUNNING_MODAL"}

    def _finish(self, context):
        wm = context.window_manager
        wm.event_timer_remove(self._timer)
        wm.progress_end()
        context.workspace.status_text_set(None)

    def modal(self, context, event):
        client = self._client
        if event.type == "ESC":
            client.cancel(self._job_id)
        if event.type != "TIMER":
            return {"PASS_THROUGH"}
        client.drain()
        state = self._state
        if state["done"] is None:
            context.window_manager.progress_update(int(100 * state["progress"]))
            context.workspace.status_text_set(f"{self.bl_label}: {100 * state['progress']:.0f}% {state['message']} (Esc to cancel)")
            return {"RUNNING_MODAL"}
        self._finish(context)
        kind, payload, out = state["done"]
        if kind == "error":
            return self._fail(payload)
        return self.apply(context, payload, out)
