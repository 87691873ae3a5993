"""Errors the engine raises for bad input: one clear line naming what is wrong.

The command line prints `error: <message>` and exits non-zero; the worker
process forwards the message to Blender's report. Anything else that escapes
is a bug and keeps its traceback.
"""


class EngineError(Exception):
    """Bad input or an impossible request; the message names the file, key or value at fault."""
