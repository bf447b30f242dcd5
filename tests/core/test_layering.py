"""The layout's rules, checked on the source: core/ never imports Blender, and every
module says what it is for."""
import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
CORE_MODULES = sorted((ROOT / "core").rglob("*.py"))
BLENDER_MODULES = {"bpy", "gpu", "mathutils", "bmesh", "bl_math", "bpy_extras", "bl_ui", "_bpy"}
# Whole packages beside core whose modules all need a module docstring.
DOCUMENTED = ("core", "operators", "panels", "gpu_shaders")


def _imported_top_modules(tree: ast.AST) -> list[tuple[int, str]]:
    """(line, top-level module name) of every absolute import, anywhere in the module
    (a function-level import counts as much as one at the top)."""
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name.split(".")[0]) for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            found.append((node.lineno, node.module.split(".")[0]))
        elif isinstance(node, ast.Call) and getattr(node.func, "attr", getattr(node.func, "id", "")) in (
                "import_module", "__import__") and node.args and isinstance(node.args[0], ast.Constant):
            found.append((node.lineno, str(node.args[0].value).split(".")[0]))
    return found


def test_core_has_modules():
    assert len(CORE_MODULES) > 20  # the glob found the package


@pytest.mark.parametrize("path", CORE_MODULES, ids=lambda p: str(p.relative_to(ROOT)))
def test_core_never_imports_blender(path):
    tree = ast.parse(path.read_text(), filename=str(path))
    offending = [(line, name) for line, name in _imported_top_modules(tree) if name in BLENDER_MODULES]
    assert not offending, f"{path.relative_to(ROOT)} imports Blender modules: {offending}"


@pytest.mark.parametrize("path", CORE_MODULES, ids=lambda p: str(p.relative_to(ROOT)))
def test_core_relative_imports_stay_inside_core(path):
    """``from ..operators import x`` would tie core to the Blender side through the back door."""
    depth = len(path.relative_to(ROOT / "core").parts)  # core/x.py: 1, core/sub/x.py: 2
    tree = ast.parse(path.read_text(), filename=str(path))
    escaping = [node.lineno for node in ast.walk(tree)
                if isinstance(node, ast.ImportFrom) and node.level > depth]
    assert not escaping, f"{path.relative_to(ROOT)} imports from outside core/ at lines {escaping}"


def test_the_checker_sees_a_blender_import(tmp_path):
    """The check above could pass by never looking: it must flag each kind of import."""
    for source in ("import bpy", "from mathutils import Vector", "def f():\n    import gpu",
                   "import importlib\nimportlib.import_module('bmesh')"):
        names = {name for _, name in _imported_top_modules(ast.parse(source))}
        assert names & BLENDER_MODULES, source


@pytest.mark.parametrize("path", sorted(p for folder in DOCUMENTED for p in (ROOT / folder).rglob("*.py")),
                         ids=lambda p: str(p.relative_to(ROOT)))
def test_every_module_says_what_it_is_for(path):
    tree = ast.parse(path.read_text(), filename=str(path))
    docstring = ast.get_docstring(tree)
    assert docstring and len(docstring.split()) >= 4, f"{path.relative_to(ROOT)} has no module docstring"
