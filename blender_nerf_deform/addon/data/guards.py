"""Every way into the add-on ends in one message, whatever went wrong in it.

Blender calls the add-on from operators (execute, invoke, modal), app handlers, timers and the
render engine. Errors that were foreseen are reported where they happen (a report naming the object
and the value at fault). An error nobody foresaw must not leave a Python traceback on the screen, a
modal timer running, a half-done job's files or a frame changed: here it runs the operator's
`clean_up_after_error(context)` when it has one, and ends in one message that names the log file
holding its traceback (engine/errors.py, `unexpected_error`):

- `guard_classes(classes)`: the operators (and the render engine) of a module, before they are
  registered (addon/__init__.py does it for every module): the operator reports the error and ends
  (CANCELLED).
- `guarded(fn)`: an app handler; its error is printed to the console once (a handler runs on
  every update, and would repeat it). `call_guarded(where, fn, ...)`: one call of a callback (the
  worker's answers, drained by a timer), the same way.
"""

from __future__ import annotations

import functools

import bpy

from ...engine.errors import unexpected_error

_GUARDED = "_nerf_deform_guarded"
_OPERATOR_METHODS = ("execute", "invoke", "modal")
_ENGINE_METHODS = ("render", "view_update", "view_draw")
_wrappers: dict = {}  # function -> its guarded wrapper (the same one each time: handlers are removed by it)
_said: set[tuple[str, str, str]] = set()


def _operator_method(fn, name: str):
    def run(self, context, *args):
        try:
            return fn(self, context, *args)
        except Exception:  # not KeyboardInterrupt or SystemExit: those end Blender's own way
            message = unexpected_error(getattr(self, "bl_label", type(self).__name__))
            clean_up = getattr(self, "clean_up_after_error", None)
            if clean_up is not None:
                try:
                    clean_up(context)
                except Exception:
                    message += "; its clean-up failed too: " + unexpected_error("clean-up")
            self.report({"ERROR"}, message)
            return {"CANCELLED"}

    # Blender checks the number of arguments a registered method takes.
    if name == "execute":

        def wrapper(self, context):
            return run(self, context)
    else:

        def wrapper(self, context, event):
            return run(self, context, event)

    functools.update_wrapper(wrapper, fn)
    setattr(wrapper, _GUARDED, True)
    return wrapper


def _engine_method(fn, name: str):
    def run(self, *args):
        try:
            return fn(self, *args)
        except Exception as error:
            message = say_once(f"NeRF Deform render engine ({name})", error)
            if name == "render" and message:
                self.report({"ERROR"}, message)
                self.error_set(message)

    if name == "render":

        def wrapper(self, depsgraph):
            return run(self, depsgraph)
    else:

        def wrapper(self, context, depsgraph):
            return run(self, context, depsgraph)

    functools.update_wrapper(wrapper, fn)
    setattr(wrapper, _GUARDED, True)
    return wrapper


def guard_classes(classes) -> None:
    """Guard the entry points of these classes (idempotent: registering again keeps one guard)."""
    for cls in classes:
        if issubclass(cls, bpy.types.Operator):
            names, wrap = _OPERATOR_METHODS, _operator_method
        elif issubclass(cls, bpy.types.RenderEngine):
            names, wrap = _ENGINE_METHODS, _engine_method
        else:
            continue
        for name in names:
            fn = getattr(cls, name, None)
            if fn is not None and not getattr(fn, _GUARDED, False):
                setattr(cls, name, wrap(fn, name))


def say_once(where: str, error: Exception) -> str:
    """The one line for `error` at `where`, its traceback logged and the line printed, the first time this
    error comes from there; "" after that."""
    try:
        text = str(error)
    except Exception:  # an exception whose own text fails is still said once
        text = ""
    key = (where, type(error).__name__, text)
    if key in _said:
        return ""
    _said.add(key)
    message = unexpected_error(where, error)
    print(message)
    return message


def guarded(fn):
    """`fn` (an app handler, a timer's or a worker callback) with its unforeseen errors said once and
    swallowed; the same wrapper for the same function (keeps `persistent` through functools.wraps)."""
    if getattr(fn, _GUARDED, False):
        return fn
    wrapper = _wrappers.get(fn)
    if wrapper is None:
        where = f"NeRF Deform: {getattr(fn, '__module__', '').rsplit('.', 1)[-1]}.{getattr(fn, '__qualname__', fn)}"

        @functools.wraps(fn)
        def wrapper(*args, **kwargs):
            try:
                return fn(*args, **kwargs)
            except Exception as error:
                say_once(where, error)
                return None

        setattr(wrapper, _GUARDED, True)
        _wrappers[fn] = wrapper
    return wrapper


def call_guarded(where: str, fn, *args):
    """`fn(*args)`, its unforeseen error said once (at `where`) and swallowed (None returned)."""
    try:
        return fn(*args)
    except Exception as error:
        say_once(where, error)
        return None
