"""The one compatibility module against the Blender it runs in (CI runs every supported one).

Each check reads the running Blender's behaviour directly, so that the module's
version table cannot drift from what Blender does.
"""
import importlib
import sys
import tomllib
from pathlib import Path

import bpy

import pytest

from tools.blender_compat import compat as tools_compat

MANIFEST = Path(__file__).resolve().parents[2] / "blender_manifest.toml"


@pytest.fixture
def compat(visibake):
    return importlib.import_module(f"{visibake.__name__}.operators.adapter.compat")


def test_the_tools_load_the_same_module_as_the_extension(compat):
    assert tools_compat.VERSION == compat.VERSION and tools_compat.MAX_NAME_BYTES == compat.MAX_NAME_BYTES


def test_the_minimum_is_the_manifest_s(compat):
    minimum = tomllib.loads(MANIFEST.read_text())["blender_version_min"]
    assert tuple(int(p) for p in minimum.split(".")) == compat.MINIMUM <= compat.VERSION


def test_names_are_cut_where_the_module_says(compat, clean_scene):
    image = bpy.data.images.new("é" * 200, 4, 4)  # 400 bytes: cut at a character boundary
    assert len(image.name.encode("utf-8")) in (compat.MAX_NAME_BYTES, compat.MAX_NAME_BYTES - 1)
    assert compat.fits_name("x" * compat.MAX_NAME_BYTES) and not compat.fits_name("x" * (compat.MAX_NAME_BYTES + 1))
    bpy.data.images.remove(image)


def test_new_materials_and_worlds_get_a_node_tree(compat, clean_scene):
    material, world = bpy.data.materials.new("Probe"), bpy.data.worlds.new("Probe")
    assert (material.node_tree is not None) == compat.NODES_ALWAYS  # what Blender itself does
    for datablock in (material, world):
        tree = compat.ensure_node_tree(datablock)
        assert tree is not None and len(tree.nodes) > 0
        assert compat.uses_nodes(datablock)
    bpy.data.materials.remove(material)
    bpy.data.worlds.remove(world)


def test_lamp_settings_missing_in_this_blender_read_as_neutral(compat, clean_scene):
    lamp = bpy.data.lights.new("Probe", "POINT")
    for name, neutral in (("normalize", True), ("exposure", 0.0), ("use_temperature", False)):
        expected = getattr(lamp, name) if hasattr(lamp, name) else neutral
        assert compat.lamp_setting(lamp, name, neutral) == expected
    assert compat.lamp_setting(lamp, "no_such_setting", 7) == 7
    bpy.data.lights.remove(lamp)


def test_openvdb_is_there_or_refused_with_what_to_upgrade(visibake, compat):
    if compat.VERSION >= (4, 5, 0):
        module = compat.openvdb()
        assert hasattr(module, "FloatGrid")
    else:
        with pytest.raises(compat.FeatureMissing, match="4.5 or later"):
            compat.openvdb()
    # Inside the extension a missing feature is the user's refusal (exit 2), not a bug.
    assert issubclass(compat.FeatureMissing, visibake.core.errors.BakeRefused)


def test_the_command_line_route_is_known(compat):
    assert compat.cli_commands_supported() == hasattr(bpy.utils, "register_cli_command")


def test_module_exit_is_marked_unsafe_exactly_before_5(compat):
    assert compat.MODULE_EXIT_IS_SAFE == (compat.VERSION >= (5, 0, 0))
    assert "bpy" in sys.modules
