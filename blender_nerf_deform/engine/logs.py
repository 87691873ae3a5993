"""Where the engine's log records go.

The engine's library modules (the stages, the worker session) log through named loggers,
`logging.getLogger(__name__)`, and configure nothing: a program that imports them decides what it
shows. The two programs the engine runs as, the command line (`cli.main`) and the worker process
(`service/worker.py`), call `log_to_stderr`: each record is one plain line on stderr, as the engine's
messages always read ("read 16 frames ...", "warning: ..."). The command line's stdout stays its
output; the worker's stderr is what the add-on forwards to Blender's console and quotes when the
worker ends unexpectedly (addon/worker/client.py).
"""

from __future__ import annotations

import logging
import sys

ENGINE_LOGGER = __name__.rpartition(".")[0]  # the engine package: every module's logger is below it


class _CurrentStderr(logging.StreamHandler):
    """A StreamHandler writing to whatever `sys.stderr` is when a record comes (the worker swaps
    streams at start; a caller may redirect it), as Python's own last-resort handler does."""

    def __init__(self):
        super().__init__(sys.stderr)

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, _value):
        pass


def log_to_stderr(level: int = logging.INFO) -> logging.Handler:
    """Show the engine's records from `level` up on stderr, one plain line each; once per process
    (a second call returns the handler already there)."""
    logger = logging.getLogger(ENGINE_LOGGER)
    logger.setLevel(level)
    for handler in logger.handlers:
        if isinstance(handler, _CurrentStderr):
            return handler
    handler = _CurrentStderr()
    handler.setFormatter(logging.Formatter("%(message)s"))
    logger.addHandler(handler)
    return handler
