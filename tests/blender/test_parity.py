"""The panel, Python and the command line run the same bake with the same settings."""
import json

import bpy

import numpy as np
import OpenEXR

from bpy_scenes import (
    assert_same_light,
    black_world,
    cube,
    grid,
    image_pixels,
    material,
    mesh_object,
    point,
    select_only,
)


def test_operator_and_command_line_agree(visibake, clean_scene, tmp_path):
    black_world()
    ground = mesh_object("Ground", grid(1.0, segments=2), material("White", (0.8, 0.8, 0.8)))
    block = mesh_object("Block", cube(0.4), material("Red", (0.7, 0.2, 0.1)), location=(0, 0, 0.4))
    point(80.0, (0.5, 0.3, 1.2), name="Lamp")
    props = bpy.context.scene.visibake
    props.preset = "DRAFT"
    props.resolution = 24  # Custom from here on
    props.passes = {"lighting", "ao"}
    props.use_cache = False
    path = tmp_path / "scene.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path), copy=True)  # the settings travel with the scene
    select_only([ground, block])
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    from_panel = {(name, p): image_pixels(f"VB_{name}_{p}") for name in ("Ground", "Block") for p in ("lighting", "ao")}
    operator_report = json.loads(bpy.context.scene["visibake_report"])

    out = tmp_path / "cli"
    report_path = tmp_path / "cli.json"
    assert visibake.cli.main(["bake", str(path), "--out", str(out), "--objects", "Ground,Block",
                              "--report", str(report_path), "--no-progress"]) == 0
    cli_report = json.loads(report_path.read_text())
    for key in ("directions", "bounces", "shadows", "passes", "rotate", "seed", "margin", "light_groups",
                "vertex_lookup", "threads"):
        assert cli_report["settings"][key] == operator_report["settings"][key], key
    for name in ("Ground", "Block"):
        for pass_name in ("lighting", "ao"):
            with OpenEXR.File(str(out / name / f"{pass_name}.exr")) as exr:
                top_down = exr.channels()["RGBA"].pixels
            # EXR rows run top-down, Blender's pixels bottom-up. The panel keeps its preparation
            # for relights and so adds the lamps' light by parts: the same light to rounding.
            # Ambient occlusion has no lamps, and is the same to the bit.
            check = assert_same_light if pass_name == "lighting" else np.testing.assert_array_equal
            check(top_down[::-1], from_panel[name, pass_name], err_msg=f"{name} {pass_name}")


def test_the_panel_s_report_lines_cover_the_report(visibake, clean_scene):
    black_world()
    ground = mesh_object("Ground", grid(1.0), material("White", (0.8, 0.8, 0.8)))
    point(80.0, (0.5, 0.3, 1.2), name="Lamp")
    bpy.context.scene.visibake.resolution = 16
    select_only([ground])
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    report = json.loads(bpy.context.scene["visibake_report"])
    lines = [text for text, _ in visibake.panels.main.report_lines(report)]
    assert any(line.startswith("visibility:") or line.startswith("samples:") for line in lines)
    assert sum(line.startswith("skipped:") for line in lines) == len(report["skipped"])
    assert any(line.startswith("rays:") for line in lines)
    # Panels are registered and poll as the scene has a report (drawing needs a window).
    assert bpy.types.VIEW3D_PT_visibake_report.poll(bpy.context)


def test_occlude_only_objects_shadow_but_get_no_results(visibake, clean_scene):
    black_world()
    mesh_object("Ground", grid(1.0), material("White", (0.8, 0.8, 0.8)))
    block = mesh_object("Block", cube(0.4), material("Red", (0.7, 0.2, 0.1)), location=(0, 0, 0.4))
    point(80.0, (0.0, 0.0, 1.5), name="Lamp")
    block.visibake.role = "OCCLUDE"
    props = bpy.context.scene.visibake
    props.bake_all, props.resolution, props.use_cache = True, 16, False
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    assert "VB_Ground_lighting" in bpy.data.images and "VB_Block_lighting" not in bpy.data.images
    report = json.loads(bpy.context.scene["visibake_report"])
    assert {o["name"]: o["output"] for o in report["objects"]} == {"Ground": True, "Block": False}
    lit = image_pixels("VB_Ground_lighting")[..., 0]
    assert lit.min() < 0.5 * lit.max()  # the block's shadow is on the ground
    # Where: the lamp straight above projects the block's top (|x|, |y| < 0.2 at 0.6 m)
    # to |x|, |y| < 0.33 on the ground, texels 5 to 10 of 16; only bounced light reaches
    # 6 to 9, whose whole footprint the shadow covers (5 and 10 straddle its edge).
    assert lit[6:10, 6:10].max() < 0.1 * lit.max()
    assert min(lit[4, 5:11].min(), lit[11, 5:11].min(), lit[5:11, 4].min(), lit[5:11, 11].min()) > 0.5 * lit.max()
    # No pass of the occluder is written, and the report says why.
    assert not [name for name in bpy.data.images.keys() if name.startswith("VB_Block")]
    assert "outputs of 1 objects that only occlude and reflect: Block" in report["skipped"]


def test_a_re_bake_reuses_an_occluder_s_in_memory_unwrap_until_the_occluder_moves(visibake, clean_scene):
    memo = visibake.operators.adapter.layout.IN_MEMORY_UNWRAPS
    memo.clear()  # another test may have unwrapped the same block
    black_world()
    mesh_object("Ground", grid(1.0), material("White", (0.8, 0.8, 0.8)))
    block = mesh_object("Block", cube(0.4), material("Red", (0.7, 0.2, 0.1)), location=(0.3, 0, 0.4))
    point(80.0, (0.0, 0.0, 1.5), name="Lamp")
    block.visibake.role = "OCCLUDE"
    while block.data.uv_layers:  # an occluder without a UV map is unwrapped in memory
        block.data.uv_layers.remove(block.data.uv_layers[0])
    props = bpy.context.scene.visibake
    props.bake_all, props.resolution, props.directions, props.use_cache = True, 32, 32, False

    def bake():
        assert bpy.ops.visibake.bake() == {"FINISHED"}
        report = json.loads(bpy.context.scene["visibake_report"])
        reason = {o["name"]: o["layout_reason"] for o in report["objects"]}["Block"]
        return reason, image_pixels("VB_Ground_lighting").copy()

    first_reason, first = bake()
    assert first_reason.startswith("unwrapped in memory") and len(memo) == 1
    again_reason, again = bake()
    assert again_reason.startswith("the in-memory unwrap of an earlier bake in this session")
    assert np.array_equal(again, first)  # the same unwrap, so the same light bounced off the block
    assert len(block.data.uv_layers) == 0
    block.location.x = -0.3
    moved_reason, moved = bake()
    assert moved_reason.startswith("unwrapped in memory") and len(memo) == 2
    assert not np.array_equal(moved, first)


def test_an_object_s_own_texel_density_sizes_its_atlas(visibake, clean_scene):
    black_world()
    mesh_object("Small", grid(0.5), material("White", (0.8, 0.8, 0.8)))
    big = mesh_object("Big", grid(2.0), material("White", (0.8, 0.8, 0.8)), location=(5, 0, 0))
    point(80.0, (0.0, 0.0, 1.5), name="Lamp")
    props = bpy.context.scene.visibake
    props.bake_all, props.resolution, props.directions, props.use_cache = True, 16, 16, False
    big.visibake.texel_density = 10.0  # 4 x 4 m with a full UV square: 40 texels a side
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    sizes = {o["name"]: o["resolution"] for o in json.loads(bpy.context.scene["visibake_report"])["objects"]}
    assert sizes["Small"] == [16, 16] and sizes["Big"] == [40, 40]


def test_every_setting_of_the_panel_and_the_preferences_has_a_command_line_option(visibake):
    cli = visibake.cli
    commands = cli.build_parser()._subparsers._group_actions[0].choices
    options = {(name, option) for name, command in commands.items() for action in command._actions
               for option in action.option_strings}
    scene_settings = (set(bpy.types.Scene.bl_rna.properties["visibake"].fixed_type.properties.keys())
                      - {"rna_type", "name"})
    assert scene_settings == set(cli.SCENE_SETTING_OPTIONS), "a scene setting without a command-line option"
    preferences = (set(visibake.operators.adapter.device.preferences().bl_rna.properties.keys())
                   - {"rna_type", "bl_idname"})
    assert preferences == set(cli.PREFERENCE_OPTIONS), "a preference without a command-line option"
    for option in [*cli.SCENE_SETTING_OPTIONS.values(), *cli.PREFERENCE_OPTIONS.values()]:
        # "--option" is the bake command's; "COMMAND --option" another command's.
        command, _, name = option.rpartition(" ") if option else ("", "", None)
        assert option is None or (command or "bake", name) in options, option


def _saved_lit_ground(tmp_path):
    """A ground plane and a lamp, saved as scene.blend (the scene stays open)."""
    black_world()
    mesh_object("Ground", grid(1.0), material("White", (0.8, 0.8, 0.8)))
    point(80.0, (0.5, 0.3, 1.2), name="Lamp")
    path = tmp_path / "scene.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path), copy=True)
    return path


def test_the_command_line_s_vertex_lookup_and_threads_reach_the_bake(visibake, clean_scene, tmp_path):
    path = _saved_lit_ground(tmp_path)
    report = tmp_path / "report.json"
    assert visibake.cli.main(["bake", str(path), "--directions", "16", "--resolution", "8", "--vertex-lookup",
                              "nearest", "--threads", "1", "--report", str(report), "--no-progress",
                              "--no-cache"]) == 0
    settings = json.loads(report.read_text())["settings"]
    assert settings["vertex_lookup"] == "nearest" and settings["threads"] == 1
    assert visibake.cli.main(["bake", str(path), "--threads", "-1", "--no-progress"]) == 2


def test_every_operator_of_the_panel_has_a_command(visibake):
    cli = visibake.cli
    registered = {cls.bl_idname for cls in visibake.operators.classes if issubclass(cls, bpy.types.Operator)}
    assert registered == set(cli.OPERATOR_COMMANDS)
    commands = cli.build_parser()._subparsers._group_actions[0].choices
    for command in cli.OPERATOR_COMMANDS.values():
        name, *options = command.split()
        assert name in commands, name
        known = {o for action in commands[name]._actions for o in action.option_strings}
        assert set(options) <= known, command


def test_the_preview_and_clear_cache_commands_do_what_the_buttons_do(visibake, clean_scene, tmp_path):
    path = _saved_lit_ground(tmp_path)
    cache = tmp_path / "cache"
    options = ["--directions", "16", "--resolution", "8", "--cache-dir", str(cache), "--no-progress"]
    assert visibake.cli.main(["bake", str(path), "--preview-nodes", *options]) == 2  # nothing to keep it in
    baked = tmp_path / "baked.blend"
    assert visibake.cli.main(["bake", str(path), "--preview-nodes", "--save", str(baked), *options]) == 0
    assert any(cache.iterdir())

    bpy.ops.wm.open_mainfile(filepath=str(baked))
    white = bpy.data.materials["White"]
    assert "VisiBake Lighting Ground" in bpy.data.node_groups
    assert any(node.get("visibake_preview") for node in white.node_tree.nodes)
    removed = tmp_path / "removed.blend"
    assert visibake.cli.main(["preview", str(baked), "--remove", "--save", str(removed)]) == 0
    bpy.ops.wm.open_mainfile(filepath=str(removed))
    assert "VisiBake Lighting Ground" not in bpy.data.node_groups
    again = tmp_path / "again.blend"
    assert visibake.cli.main(["preview", str(removed), "--save", str(again)]) == 0
    bpy.ops.wm.open_mainfile(filepath=str(again))
    assert "VisiBake Lighting Ground" in bpy.data.node_groups

    assert visibake.cli.main(["clear-cache", str(path), "--cache-dir", str(cache)]) == 0
    assert not any(p.is_file() for p in cache.rglob("*"))
