"""Ending an engine process once its work is done, without tearing its interpreter down.

An interpreter that imported torch takes about half a second to tear down (measured on the project's
2-core machine: `python -c "import torch"` 1.7 s, 1.1 s when it leaves through os._exit): it frees
every module's objects one by one, memory the system takes back at once anyway. A one-frame `render`
paid that on every run, and Blender waits for it whenever it stops the worker. When a command has
returned, everything it wrote is closed (files are written to a temporary name and renamed, messages
flushed one by one); `exit_process` then runs what was registered to run at exit (atexit: logging's
shutdown, tempfile's and weakref's finalizers), flushes the standard streams and ends the process with
the command's code. While a non-daemon thread still runs it exits the ordinary way, which waits for it.
"""

from __future__ import annotations

import atexit
import os
import sys
import threading
from typing import NoReturn


def exit_process(code: int | None) -> NoReturn:
    code = int(code or 0)
    if any(t.is_alive() and not t.daemon and t is not threading.main_thread() for t in threading.enumerate()):
        sys.exit(code)
    atexit._run_exitfuncs()  # what the interpreter's own exit would run first (not public, stable since 3.0)
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (AttributeError, OSError, ValueError):  # None, a closed pipe, a closed file
            pass
    os._exit(code)
