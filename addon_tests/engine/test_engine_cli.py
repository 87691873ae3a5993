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
