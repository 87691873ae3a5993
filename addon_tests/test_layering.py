"""The layering rule of DESIGN.md, read from the source: engine/ has no bpy, addon/ has no torch."""

from pathlib import Path

from tools.check_layering import violations

from conftest import REPO


def test_project_respects_layering():
    assert violations(REPO / "blender_nerf_deform") == []


def _write(root: Path, rel: str, text: str) -> None:
    path = root / rel
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)


def _fake_package(tmp_path: Path) -> Path:
    root = tmp_path / "blender_nerf_deform"
    for rel in ("__init__.py", "engine/__init__.py", "addon/__init__.py"):
        _write(root, rel, "")
    return root


def test_checker_catches_bpy_in_engine_even_inside_a_function(tmp_path):
    root = _fake_package(tmp_path)
    _write(root, "engine/stage.py", "def f():\n    from bpy import types\n")
    (problem,) = violations(root)
    assert "engine/stage.py:2" in problem and "bpy" in problem


def test_checker_catches_torch_in_addon(tmp_path):
    root = _fake_package(tmp_path)
    _write(root, "addon/ops.py", "import numpy\nimport torch.nn as nn\n")
    (problem,) = violations(root)
    assert "addon/ops.py:2" in problem and "torch" in problem


def test_checker_catches_torch_reached_through_an_engine_module(tmp_path):
    root = _fake_package(tmp_path)
    _write(root, "engine/field.py", "import torch\n")
    _write(root, "engine/formats.py", "from . import field\n")
    _write(root, "addon/ops.py", "from ..engine import formats\n")
    problems = violations(root)
    assert any("reaches torch" in p and "formats" in p and "field" in p for p in problems), problems


def test_checker_catches_a_library_blender_lacks_reached_through_an_engine_module(tmp_path):
    root = _fake_package(tmp_path)
    _write(root, "engine/cage.py", "import numpy as np\n\ndef build():\n    import pytetwild\n")
    _write(root, "addon/ops.py", "from ..engine.cage import build\n")
    (problem,) = violations(root)
    assert "reaches pytetwild" in problem and "addon/ops.py:1" in problem


def test_checker_catches_a_third_party_import_in_addon(tmp_path):
    root = _fake_package(tmp_path)
    _write(root, "addon/io.py", "import bpy, bmesh\nfrom PIL import Image\n")
    (problem,) = violations(root)
    assert "addon/io.py:2" in problem and "PIL" in problem


def test_checker_allows_pure_numpy_engine_modules_in_addon(tmp_path):
    root = _fake_package(tmp_path)
    _write(root, "engine/embedding.py", "import numpy as np\n")
    _write(root, "addon/ops.py", "import bpy\nfrom ..engine.embedding import np\n")
    assert violations(root) == []
