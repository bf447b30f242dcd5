"""One settings path: core's table defines the properties and the options, and one
function turns arguments, the scene and the preferences into a bake's settings."""
import json

import bpy

import pytest

from bpy_scenes import black_world, grid, material, mesh_object, point, select_only


@pytest.fixture
def prefs(visibake):
    prefs = visibake.operators.adapter.device.preferences()
    saved = {name: getattr(prefs, name) for name in ("threads", "device", "cache_dir")}
    yield prefs
    for name, value in saved.items():
        setattr(prefs, name, value)


def _groups(visibake):
    settings = visibake.core.settings
    return [(bpy.types.Scene.bl_rna.properties["visibake"].fixed_type, settings.SETTINGS),
            (bpy.types.Object.bl_rna.properties["visibake"].fixed_type, settings.OBJECT_SETTINGS),
            (visibake.operators.adapter.device.preferences().bl_rna, settings.PREFERENCE_SETTINGS)]


def test_the_properties_are_core_s_settings(visibake):
    checked = 0
    for group, table in _groups(visibake):
        for prop in group.properties:
            spec = table.get(prop.identifier)
            if spec is None:
                continue
            checked += 1
            where = f"{group.identifier}.{prop.identifier}"
            assert (prop.name, prop.description) == (spec.title, spec.help), where
            if prop.type == "ENUM":
                items = [(i.identifier, i.name, i.description) for i in prop.enum_items]
                assert items == list(spec.choices), where
                default = set(prop.default_flag) if prop.is_enum_flag else prop.default
                assert default == (set(spec.default) if spec.type is tuple else spec.default), where
            else:
                assert prop.default == spec.default, where
            if prop.type in ("INT", "FLOAT") and spec.minimum is not None:
                assert prop.hard_min == spec.minimum, where
            if prop.type in ("INT", "FLOAT") and spec.soft_max is not None:
                assert prop.soft_max == pytest.approx(spec.soft_max), where
    on_scene = {name for name, spec in visibake.core.settings.SETTINGS.items() if spec.on_scene}
    assert checked >= len(on_scene) + 4 + 4  # every scene setting, the object's four, four preferences


def test_the_command_line_s_choices_are_core_s(visibake):
    settings = visibake.core.settings
    bake = visibake.cli.build_parser()._subparsers._group_actions[0].choices["bake"]
    choices = {option: action.choices for action in bake._actions for option in action.option_strings}
    assert tuple(choices["--mode"]) == settings.LAYOUT_MODES
    assert tuple(choices["--shadows"]) == settings.SHADOW_MODES
    assert tuple(choices["--vertex-lookup"]) == settings.VERTEX_LOOKUPS
    assert tuple(choices["--device"]) == settings.DEVICES
    assert {c.upper() for c in choices["--preset"]} == set(settings.PRESETS)


def test_the_argument_wins_then_the_scene_then_the_preference(visibake, clean_scene, prefs):
    resolve = visibake.operators.adapter.settings.resolve
    props = bpy.context.scene.visibake
    cores = visibake.core.settings.CPU_COUNT  # the preference offers no more threads than cores
    prefs.threads, prefs.device = cores, "cpu"
    resolved = resolve(bpy.context)
    assert (resolved.bake.threads, resolved.device, resolved.refine) == (cores, "cpu", False)
    props.refine_vertex_objects = True
    props.directions, props.resolution, props.mode = 40, 20, "vertex"
    resolved = resolve(bpy.context)
    assert resolved.refine and resolved.bake.directions == 40
    assert (resolved.layout.resolution, resolved.layout.mode) == (20, "vertex")
    resolved = resolve(bpy.context, threads=0, device="auto", refine=False)
    assert (resolved.bake.threads, resolved.device, resolved.refine) == (0, "auto", False)


def test_a_complete_set_is_refused_once_with_core_s_message(visibake, clean_scene, prefs):
    resolve = visibake.operators.adapter.settings.resolve
    bpy.context.scene.visibake.passes = set()  # the panel allows it; a bake cannot
    with pytest.raises(visibake.core.errors.BakeRefused, match="^passes: choose at least one of"):
        resolve(bpy.context)
    bpy.context.scene.visibake.passes = {"ao"}
    with pytest.raises(visibake.core.errors.BakeRefused, match="^device must be one of auto, gpu, cpu"):
        resolve(bpy.context, device="tpu")


def test_the_panel_s_bake_uses_the_preferences(visibake, clean_scene, prefs, tmp_path):
    black_world()
    ground = mesh_object("Ground", grid(1.0), material("White", (0.8, 0.8, 0.8)))
    point(80.0, (0.5, 0.3, 1.2), name="Lamp")
    props = bpy.context.scene.visibake
    props.directions, props.resolution, props.use_cache = 16, 8, False
    threads = min(2, visibake.core.settings.CPU_COUNT)
    prefs.threads, prefs.device = threads, "cpu"
    select_only([ground])
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    report = json.loads(bpy.context.scene["visibake_report"])
    assert report["settings"]["threads"] == threads and report["device"]["requested"] == "cpu"


def test_a_command_line_value_is_refused_by_core_s_rule_before_blender_clamps_it(visibake, clean_scene, tmp_path,
                                                                                   capfd):
    path = tmp_path / "empty.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path), copy=True)
    assert visibake.cli.main(["bake", str(path), "--seed", "-1", "--no-progress"]) == 2
    assert capfd.readouterr().err.strip().splitlines()[-1] == "visibake: error: --seed must be >= 0, got -1"
    assert visibake.cli.main(["bake", str(path), "--passes", ",", "--no-progress"]) == 2
    assert "--passes: choose at least one of lighting" in capfd.readouterr().err
