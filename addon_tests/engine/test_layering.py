"""The layering rule (docs/ARCHITECTURE.md), read from the source: engine/ has no bpy, addon/ has no torch."""

import shutil
from pathlib import Path

from fixtures import REPO

from tools.check_layering import violations as check


def violations(root: Path, addon_layers=None) -> list[str]:
    """The checker on a made-up package (its add-on modules are not the project's: no layer table)."""
    return check(root, addon_layers=addon_layers)


def test_project_respects_layering():
    assert check(REPO / "blender_nerf_deform") == []


LAYERS = ("data", "worker", "edit", "ui")


def test_checker_catches_an_import_cycle_in_the_addon_through_a_function(tmp_path):
    root = _fake_package(tmp_path)
    _write(root, "addon/data/store.py", "import bpy\n")
    _write(root, "addon/edit/ops.py", "from ..data.store import x\n")
    _write(root, "addon/worker/client.py", "def f():\n    from ..edit.ops import y\n")
    _write(root, "addon/data/store.py", "from ..worker.client import z\n")
    problems = violations(root)
    assert any("import cycle in addon/" in p for p in problems), problems


def test_checker_catches_an_addon_import_from_a_higher_layer(tmp_path):
    root = _fake_package(tmp_path)
    _write(root, "addon/data/store.py", "")
    _write(root, "addon/ui/panel.py", "from ..data.store import prop\n")  # ui -> data: down, allowed
    _write(
        root, "addon/edit/ops.py", "from ..data import store\n\ndef f():\n    from ..ui.panel import draw\n"
    )  # edit -> ui: up
    (problem,) = violations(root, LAYERS)
    assert "addon/edit/ops.py:4" in problem and "(edit) imports" in problem and "(ui)" in problem


def test_checker_asks_for_a_new_addon_module_s_layer(tmp_path):
    root = _fake_package(tmp_path)
    _write(root, "addon/data/store.py", "")
    _write(root, "addon/newcomer.py", "from .data import store\n")
    _write(root, "addon/tools/helper.py", "")
    problems = violations(root, LAYERS)
    assert len(problems) == 2 and all("is in no layer" in p for p in problems), problems
    assert any("addon.newcomer" in p for p in problems) and any("addon.tools.helper" in p for p in problems)


def test_checker_catches_an_upward_import_planted_in_the_project(tmp_path):
    """The project's own add-on, copied, with one import from the data layer up to render inside a
    function (where a lazy import would hide it from Python's own cycle errors)."""
    root = tmp_path / "blender_nerf_deform"
    shutil.copytree(REPO / "blender_nerf_deform", root, ignore=shutil.ignore_patterns("__pycache__"))
    assert check(root) == []
    properties = root / "addon" / "data" / "properties.py"
    properties.write_text(properties.read_text() + "\n\ndef _planted():\n    from ..render.frame import nerf_pose\n")
    problems = check(root)
    assert any(
        "addon/data/properties.py:" in p and "(data) imports" in p and "frame (render)" in p for p in problems
    ), problems
    assert any("import cycle in addon/" in p for p in problems), problems  # render's modules import properties


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


def test_checker_catches_an_import_cycle_in_the_engine(tmp_path):
    root = _fake_package(tmp_path)
    _write(root, "engine/nerf/__init__.py", "")
    _write(root, "engine/nerf/a.py", "from . import b\n")
    _write(root, "engine/nerf/b.py", "def f():\n    from .a import g\n")
    (problem,) = violations(root)
    assert "import cycle" in problem and "nerf.a" in problem and "nerf.b" in problem


def test_checker_catches_stage_logic_in_the_plumbing(tmp_path):
    root = _fake_package(tmp_path)
    _write(root, "engine/cli/__init__.py", "")
    _write(root, "engine/cli/cage.py", "import numpy as np\n\ndef main(args):\n    import pytetwild\n")
    _write(root, "engine/service/__init__.py", "")
    _write(root, "engine/service/ops.py", "import torch\n")
    problems = violations(root)
    assert len(problems) == 2
    assert any("engine/cli/cage.py:4" in p and "pytetwild" in p for p in problems)
    assert any("engine/service/ops.py:1" in p and "torch" in p for p in problems)


def test_checker_catches_a_stage_importing_the_plumbing(tmp_path):
    root = _fake_package(tmp_path)
    _write(root, "engine/service/__init__.py", "")
    _write(root, "engine/service/worker.py", "")
    _write(root, "engine/geometry/__init__.py", "")
    _write(root, "engine/geometry/cage.py", "from ..service import worker\n")
    (problem,) = [p for p in violations(root) if "stage module" in p]
    assert "engine/geometry/cage.py:1" in problem


def test_checker_follows_an_import_through_the_packages_above_it(tmp_path):
    root = _fake_package(tmp_path)
    _write(root, "engine/geometry/__init__.py", "import torch\n")
    _write(root, "engine/geometry/embedding.py", "import numpy as np\n")
    _write(root, "addon/ops.py", "from ..engine.geometry.embedding import np\n")
    (problem,) = violations(root)
    assert "reaches torch" in problem and "addon/ops.py:1" in problem


def test_engine_tests_never_import_blender():
    """The engine half of the suite runs without Blender: no test module there imports bpy."""
    import ast

    from tools.check_layering import BLENDER_MODULES

    found = []
    for path in sorted((REPO / "addon_tests" / "engine").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            names = (
                [a.name for a in node.names]
                if isinstance(node, ast.Import)
                else [node.module or ""]
                if isinstance(node, ast.ImportFrom) and node.level == 0
                else []
            )
            found += [f"{path.name}:{node.lineno} {n}" for n in names if n.split(".")[0] in BLENDER_MODULES]
    assert found == []
