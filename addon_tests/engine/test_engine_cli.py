"""The engine's command line runs in plain Python, without Blender."""

import subprocess
import sys

from fixtures import REPO

COMMANDS = ("train", "eval", "render", "extract", "cage", "prepare", "compile")

# Runs the CLI with bpy made unimportable, then reports which heavy modules got loaded.
_RUN_WITHOUT_BPY = """
import runpy, sys
sys.modules["bpy"] = None  # any `import bpy` now raises ImportError
sys.argv = ["blender_nerf_deform.engine", *sys.argv[1:]]
try:
    runpy.run_module("blender_nerf_deform.engine", run_name="__main__")
finally:
    print("LOADED:", sorted(m for m in ("bpy", "torch") if sys.modules.get(m)), file=sys.stderr)
"""


def _cli(*args):
    return subprocess.run([sys.executable, "-c", _RUN_WITHOUT_BPY, *args], cwd=REPO, capture_output=True, text=True)


def test_help_lists_the_design_commands_without_bpy_or_torch():
    proc = _cli("--help")
    assert proc.returncode == 0, proc.stderr
    for command in COMMANDS:
        assert f"    {command} " in proc.stdout
    assert "LOADED: []" in proc.stderr


def test_each_command_has_the_design_options():
    expected = {
        "train": ["--data", "--out", "--max-seconds", "--steps", "--device"],
        "eval": ["--nerf", "--data"],
        "render": ["--nerf", "--cameras", "--out", "--cage", "--deformed"],
        "extract": ["--nerf", "--out", "--threshold", "--resolution", "--min-volume"],
        "cage": ["--nerf", "--mesh", "--out"],
        "prepare": ["--images", "--out"],
    }
    for command, options in expected.items():
        proc = _cli(command, "--help")
        assert proc.returncode == 0, proc.stderr
        for option in options:
            assert option in proc.stdout, (command, option)


def test_unknown_command_fails_with_usage():
    proc = _cli("bake")
    assert proc.returncode == 2
    assert "invalid choice: 'bake'" in proc.stderr


# A process that ends through exit_process (as `python -m blender_nerf_deform.engine` and the worker do):
# exit handlers registered, a temporary folder left to its finalizer, output unflushed, and (with an
# argument) a non-daemon thread that finishes writing a file after the main thread is done.
_EXIT_PROCESS = """
import atexit, sys, tempfile, threading, time
from blender_nerf_deform.engine.process_exit import exit_process
atexit.register(lambda: print("exit handler ran"))
folder = tempfile.TemporaryDirectory()
print("folder", folder.name, end="")  # no newline: stays in the pipe's buffer
sys.stderr.write("to stderr")
if len(sys.argv) > 1:
    def late():
        time.sleep(1.0)
        open(sys.argv[1], "w").write("written")
    threading.Thread(target=late).start()
exit_process(3)
"""


def test_exit_process_runs_exit_handlers_flushes_and_keeps_the_code(tmp_path):
    from pathlib import Path

    proc = subprocess.run([sys.executable, "-c", _EXIT_PROCESS], cwd=REPO, capture_output=True, text=True)
    assert proc.returncode == 3, proc.stderr
    assert proc.stdout.startswith("folder ") and "exit handler ran" in proc.stdout
    assert proc.stderr == "to stderr"
    assert not Path(proc.stdout.split()[1]).exists()  # tempfile's finalizer ran
    # A non-daemon thread still running: the ordinary exit, which waits for it.
    marker = tmp_path / "late.txt"
    proc = subprocess.run([sys.executable, "-c", _EXIT_PROCESS, str(marker)], cwd=REPO, capture_output=True, text=True)
    assert proc.returncode == 3 and marker.read_text() == "written", proc.stderr
