"""The package layout holds: each room imports only what its ``__init__`` allows, rclpy stays in the
ROS room, public names and entry points keep working, and the README's Python examples run."""
from __future__ import annotations

import ast
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "uw_sil"

# room -> rooms of uw_sil it may import (besides itself). "" is the package root (uw_sil/__init__.py).
ALLOWED = {
    "_shared": set(),
    "sim": {"_shared"},
    "metrics": {"_shared"},
    "bags": {"sim", "_shared"},
    "viz": {"_shared"},
    "fit": {"sim", "metrics", "bags", "_shared", "viz"},
    "enhance": {"sim", "metrics", "bags", "_shared", "viz"},
    "campaign": {"cli", "_shared"},   # runs the `uw-sil` commands per dive, reads the files they write
    "nodes": {"sim", "metrics", "bags", "fit", "enhance", "_shared", "viz"},
    "cli": {"sim", "metrics", "bags", "fit", "enhance", "nodes", "_shared", "viz", "campaign"},
    "": {"sim", "metrics", "bags", "fit", "enhance", "_shared", "viz"},
}
ROS_MODULES = {"rclpy", "rcl_interfaces", "sensor_msgs", "geometry_msgs", "std_msgs", "std_srvs", "rosgraph_msgs",
               "builtin_interfaces", "launch", "launch_ros", "tf2_msgs", "message_filters", "cv_bridge"}


def _room(path: Path) -> str:
    rel = path.relative_to(PKG)
    if len(rel.parts) == 1:
        return "" if rel.name == "__init__.py" else rel.stem
    return rel.parts[0]


def _imports(path: Path):
    """(absolute module name, line) of every import in a module, relative ones resolved."""
    tree = ast.parse(path.read_text(), str(path))
    rel = path.relative_to(ROOT).with_suffix("")
    pkg_parts = list(rel.parts[:-1]) if rel.name != "__init__" else list(rel.parts[:-1])
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                yield a.name, node.lineno
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = pkg_parts[: len(pkg_parts) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
                if node.module is None:   # from . import x: each name may be a module
                    for a in node.names:
                        yield mod + "." + a.name, node.lineno
                    continue
            else:
                mod = node.module
            yield mod, node.lineno


MODULES = sorted(p for p in PKG.rglob("*.py"))


@pytest.mark.parametrize("path", MODULES, ids=lambda p: str(p.relative_to(PKG)))
def test_import_rules(path):
    room = _room(path)
    allowed = ALLOWED[room] | {room}
    bad = []
    for mod, line in _imports(path):
        top = mod.split(".")[0]
        if top in ROS_MODULES and room != "nodes":
            bad.append(f"line {line}: {mod} (ROS imports belong in uw_sil.nodes)")
        if top == "uw_sil":
            parts = mod.split(".")
            target = parts[1] if len(parts) > 1 else ""
            if target == "__version__":
                continue
            if target not in allowed:
                bad.append(f"line {line}: {mod} (room {room or 'uw_sil'} may import {sorted(allowed)})")
    assert not bad, f"{path.relative_to(ROOT)} breaks the layout's import rules:\n" + "\n".join(bad)


def test_every_room_says_what_it_is_for():
    for init in PKG.glob("*/__init__.py"):
        doc = ast.get_docstring(ast.parse(init.read_text()))
        if init.parent.name == "models":
            continue
        assert doc and "Import rules" in doc, f"{init} must open with what the room is for and its import rules"


def test_no_cross_module_private_calls():
    """A module uses no other module's private names (``_name``): shared helpers are public in their room."""
    bad = []
    for path in MODULES:
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and (node.level or (node.module or "").startswith("uw_sil")):
                for a in node.names:
                    if a.name.startswith("_") and not a.name.startswith("__") and a.name != "_shared":
                        bad.append(f"{path.relative_to(ROOT)}:{node.lineno} imports {a.name}")
    assert not bad, "\n".join(bad)


PUBLIC = ["CameraModel", "Renderer", "SimCamera", "UnderwaterParams", "facing_pose", "fit_bag", "read_samples",
          "synthesize_trial", "write_trial"]


def test_public_names_resolve():
    import uw_sil

    for name in PUBLIC:
        assert getattr(uw_sil, name) is not None, name
    for room in ("sim", "metrics", "fit", "bags", "_shared"):
        mod = __import__(f"uw_sil.{room}", fromlist=["__all__"])
        assert list(mod.__all__) == sorted(mod.__all__), f"uw_sil.{room}.__all__ is not sorted"
        for name in mod.__all__:
            assert getattr(mod, name) is not None, f"uw_sil.{room}.{name}"
    with pytest.raises(AttributeError):
        uw_sil.no_such_name  # noqa: B018


def test_import_uw_sil_is_light():
    """``import uw_sil`` (and each room) loads neither pyrender, trimesh, rclpy nor OpenCV."""
    code = ("import sys, uw_sil, uw_sil.sim, uw_sil.metrics, uw_sil.fit, uw_sil.bags, uw_sil.nodes; "
            "print([m for m in ('pyrender', 'trimesh', 'rclpy', 'cv2', 'cma') if m in sys.modules])")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


def _console_scripts():
    text = (ROOT / "setup.py").read_text()
    return re.findall(r'"([\w-]+) = (uw_sil[\w.]*):(\w+)"', text)


@pytest.mark.parametrize("script,module,func", _console_scripts())
def test_entry_points_start(script, module, func):
    """Every console script's function runs its ``--help`` path (nodes print their topics and parameters)."""
    code = f"import sys; from {module} import {func}; sys.argv = [{script!r}, '--help']; sys.exit({func}())"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                         cwd=ROOT, env={**os.environ, "PYOPENGL_PLATFORM": "osmesa"})
    assert out.returncode == 0, out.stderr
    assert "usage" in out.stdout.lower()
    assert "Traceback" not in out.stderr


def _readme_python_blocks():
    text = (ROOT / "README.md").read_text()
    return re.findall(r"```python\n(.*?)```", text, flags=re.S)


@pytest.mark.parametrize("i", range(len(_readme_python_blocks())))
def test_readme_python_examples_run(i, tmp_path):
    code = _readme_python_blocks()[i]
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=tmp_path,
                         env={**os.environ, "PYOPENGL_PLATFORM": "osmesa"})
    assert out.returncode == 0, f"README example {i} failed:\n{code}\n{out.stderr[-2000:]}"
