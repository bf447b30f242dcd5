"""Hostile names (objects, light groups, setups, long and non-ASCII names) through every writer.

Every file lands inside --out, no two outputs share a path (compared the way a
case-insensitive, normalising disk compares), the report names what was renamed, and the
images of re-bakes are the same images, found again by preview.
"""
import json
import os
import unicodedata

import bpy

import pytest

from bpy_scenes import black_world, grid, material, mesh_object, point, select_only

NFC_E, NFD_E = unicodedata.normalize("NFC", "é"), unicodedata.normalize("NFD", "é")
HOSTILE_OBJECTS = ["a/b", "a_b", "a:b", "A_B", "CON", "nul.txt", "trailing.", "x/../../../../ESCAPED", "..",
                   NFC_E, NFD_E, "🙂 emoji", "A", "A_lighting"]
HOSTILE_GROUPS = ["x/+", "x/../../../../ESCAPED", "direct", "CON", "a:b"]
HOSTILE_SETUPS = ["a/b", "a:b", "A_B", "..", "CON", "x/../../../../ESCAPED", "trailing."]


def _disk_key(path):
    """A path as Windows and macOS compare it: case folded, NFC."""
    return unicodedata.normalize("NFC", unicodedata.normalize("NFC", os.path.realpath(path)).casefold())


def _long_names(visibake):
    """Object names whose images would not fit Blender's name limit (they fit themselves)."""
    limit = visibake.operators.adapter.compat.MAX_NAME_BYTES
    return ["n" * (limit - 6), "n" * (limit - 6) + "é", "m" * (limit - 2)]


def _hostile_scene(visibake):
    black_world()
    objects = []
    for index, name in enumerate(HOSTILE_OBJECTS + _long_names(visibake)):
        obj = mesh_object(name, grid(0.4), material("White", (0.8, 0.8, 0.8)), location=(index % 5, index // 5, 0))
        assert obj.name == name, (obj.name, name)
        objects.append(obj)
    for index, group in enumerate(HOSTILE_GROUPS):
        lamp = point(200.0, (index, 1.0, 2.0), name=f"Lamp{index}")
        lamp.lightgroup = group
    props = bpy.context.scene.visibake
    props.directions, props.bounces, props.resolution, props.use_cache = 8, 0, 8, False
    return objects


def _walk(folder):
    return [os.path.join(root, name) for root, _, names in os.walk(folder) for name in names]


def _assert_all_inside_and_distinct(tmp_path, out, listed, chosen=()):
    """Every listed file exists inside ``out``, but for the ``chosen`` paths (--save, --report)."""
    chosen = {os.path.realpath(p) for p in chosen}
    listed = [p for p in listed if os.path.realpath(p) not in chosen]
    out_real = os.path.realpath(out)
    for path in listed:
        assert os.path.isfile(path), path
        assert os.path.commonpath([out_real, os.path.realpath(path)]) == out_real, path
    assert len({_disk_key(p) for p in listed}) == len(listed), "two outputs share a path"
    on_disk = _walk(out)
    assert sorted(map(os.path.realpath, on_disk)) == sorted(map(os.path.realpath, listed))
    # Nothing escaped: the only files outside --out are the test's own.
    outside = [p for p in _walk(tmp_path) if os.path.commonpath([out_real, os.path.realpath(p)]) != out_real]
    assert not [p for p in outside if "ESCAPED" in p or not p.endswith((".blend", ".json", ".blend1"))], outside


@pytest.fixture
def hostile_blend(visibake, clean_scene, tmp_path):
    _hostile_scene(visibake)
    path = tmp_path / "hostile.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path), copy=True)
    return path


def test_cli_bake_with_light_groups_writes_every_file_inside_out_and_apart(visibake, hostile_blend, tmp_path):
    out = tmp_path / "a" / "b" / "c" / "out"
    report_path = tmp_path / "report.json"
    saved = tmp_path / "saved.blend"
    status = visibake.cli.main(["bake", str(hostile_blend), "--out", str(out), "--report", str(report_path),
                                "--save", str(saved), "--light-groups", "--passes", "lighting,direct", "--previews",
                                "--resolution", "8", "--directions", "8", "--bounces", "0", "--no-cache",
                                "--no-progress"])
    assert status == 0
    report = json.loads(report_path.read_text())
    files = [p for p in report["files"] if os.path.realpath(p) != os.path.realpath(saved)]
    _assert_all_inside_and_distinct(tmp_path, out, files)
    assert str(out / "visibake-bake.json") in files  # the folder's record (core.outputs.ownership)
    files.remove(str(out / "visibake-bake.json"))
    names = HOSTILE_OBJECTS + _long_names(visibake)
    # One folder per object, each its own; every object has all its passes.
    folders = {os.path.dirname(p) for p in files}
    assert len(folders) == len(names)
    passes_per_object = {len([p for p in files if os.path.dirname(p) == f and p.endswith(".exr")]) for f in folders}
    assert len(passes_per_object) == 1 and passes_per_object.pop() >= 2 * len(HOSTILE_GROUPS)
    renamed = {(r["kind"], r["name"]) for r in report["renamed_outputs"]}
    for name in ("a/b", "a:b", "CON", "nul.txt", "trailing.", "x/../../../../ESCAPED", "..", NFD_E):
        assert ("object", name) in renamed, name
    for name in _long_names(visibake):
        # Too long for an image name beside its pass; a folder name only past the component cap.
        assert ("image", f"{name}: lighting") in renamed
        too_long = len(name.encode()) > visibake.core.outputs.names.MAX_COMPONENT_BYTES
        assert (("object", name) in renamed) == too_long
    # a_b and A_B are safe names but one file on a case-insensitive disk: both are told apart.
    assert ("object", "a_b") in renamed and ("object", "A_B") in renamed
    assert ("object", NFC_E) not in renamed and ("object", "A") not in renamed  # safe names kept as they are
    assert any(kind == "pass" and "ESCAPED" in name for kind, name in renamed)
    assert any("output name(s) changed" in w for w in report["warnings"])
    assert not [p for p in _walk(tmp_path) if os.path.basename(p).startswith("ESCAPED")]

    # The images: one per (object, pass), none cut, none shared, each holding its (object, pass).
    bpy.ops.wm.open_mainfile(filepath=str(saved))
    writeback = visibake.operators.adapter.writeback
    limit = visibake.operators.adapter.compat.MAX_NAME_BYTES
    held = {}
    for image in bpy.data.images:
        if image.get("visibake_image"):
            pair = (image["visibake_object"], image["visibake_pass"])
            assert pair not in held.values() and len(image.name.encode()) <= limit
            held[image.name] = pair
    assert {obj for obj, _ in held.values()} == set(names)
    assert held[writeback.image_name("A", "lighting_direct")] == ("A", "lighting_direct")
    assert held[writeback.image_name("A_lighting", "direct")] == ("A_lighting", "direct")
    for obj, pass_name in held.values():
        assert writeback.find_image(obj, pass_name).name == writeback.image_name(obj, pass_name)


def test_cli_setups_get_distinct_folders_inside_out(visibake, hostile_blend, tmp_path):
    setups = tmp_path / "setups.json"
    setups.write_text(json.dumps({"setups": [
        {"name": name, "lights": [{"type": "SUN", "name": "S", "strength": 1.0 + i, "elevation": 40, "azimuth": 0}]}
        for i, name in enumerate(HOSTILE_SETUPS)]}))
    out = tmp_path / "out"
    report_path = tmp_path / "report.json"
    status = visibake.cli.main(["bake", str(hostile_blend), "--out", str(out), "--report", str(report_path),
                                "--setups", str(setups), "--objects", "a/b,a_b,CON", "--resolution", "8",
                                "--directions", "8", "--bounces", "0", "--no-cache", "--no-progress"])
    assert status == 0
    report = json.loads(report_path.read_text())
    _assert_all_inside_and_distinct(tmp_path, out, report["files"])
    top = {os.path.relpath(p, out).split(os.sep)[0] for p in report["files"]}
    assert len(top) == len(HOSTILE_SETUPS)
    assert len(report["files"]) == len(HOSTILE_SETUPS) * 4  # 3 objects' lighting and the setup's record
    renamed = {r["name"] for r in report["renamed_outputs"] if r["kind"] == "setup"}
    assert renamed == {"a/b", "a:b", "..", "CON", "x/../../../../ESCAPED", "trailing."}


@pytest.mark.parametrize("link", ["Ground", "Ground/lighting.exr"])
def test_an_output_path_that_links_outside_is_refused_before_anything_is_written(visibake, clean_scene, tmp_path,
                                                                                 link):
    black_world()
    ground = mesh_object("Ground", grid(1.0), material("White", (0.8, 0.8, 0.8)))
    point(100.0, (0, 0, 2))
    props = bpy.context.scene.visibake
    props.directions, props.bounces, props.resolution, props.use_cache = 8, 0, 8, False
    out, elsewhere = tmp_path / "out", tmp_path / "elsewhere"
    elsewhere.mkdir()
    if link == "Ground":  # the object's folder is a link to a folder elsewhere
        out.mkdir()
        (elsewhere / "target").mkdir()
    else:  # its pass file is a (dangling) link to a file elsewhere
        (out / "Ground").mkdir(parents=True)
    os.symlink(elsewhere / "target", out / link)
    images = set(bpy.data.images.keys())
    with pytest.raises(visibake.core.errors.OutputRefused, match="outside the output folder"):
        visibake.operators.adapter.job.run_bake(bpy.context, [ground], str(out))
    assert _walk(elsewhere) == [] and set(bpy.data.images.keys()) == images


def test_operator_rebakes_reuse_the_same_images_and_preview_finds_them(visibake, clean_scene, tmp_path):
    objects = _hostile_scene(visibake)
    props = bpy.context.scene.visibake
    props.light_groups, props.passes = True, {"lighting", "direct"}
    props.output_dir = str(tmp_path / "out")
    select_only(objects)
    props.bake_all = False

    def owned():
        return sorted(i.name for i in bpy.data.images if i.get("visibake_image"))

    assert bpy.ops.visibake.bake() == {"FINISHED"}
    first = owned()
    files = json.loads(bpy.context.scene["visibake_report"])["files"]
    _assert_all_inside_and_distinct(tmp_path, tmp_path / "out", files)
    images = len(bpy.data.images)
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    assert owned() == first and len(bpy.data.images) == images
    assert len(first) == len({(bpy.data.images[n]["visibake_object"], bpy.data.images[n]["visibake_pass"])
                              for n in first})

    # Preview wires each object's own lighting image, long names included.
    assert bpy.ops.visibake.preview_add() == {"FINISHED"}
    writeback = visibake.operators.adapter.writeback
    for obj in objects:
        tree = obj.material_slots[0].material.node_tree
        groups = [n.node_tree for n in tree.nodes if n.bl_idname == "ShaderNodeGroup" and n.get("visibake_preview")]
        assert groups, obj.name
        [image_node] = [n for n in groups[0].nodes if n.bl_idname == "ShaderNodeTexImage"]
        assert image_node.image == writeback.find_image(obj.name, "lighting")
        assert image_node.image["visibake_object"] == obj.name


def _coarse_plane_under_a_spot(visibake):
    black_world()
    limit = visibake.operators.adapter.compat.MAX_NAME_BYTES
    # "<name> (VisiBake refined)" would not fit: Blender would cut it.
    plane = mesh_object("P" * (limit - 10), grid(1.0, segments=2), material("White", (0.6, 0.6, 0.6)))
    spot = bpy.data.objects.new("Spot", bpy.data.lights.new("Spot", "SPOT"))
    spot.data.energy, spot.data.spot_size, spot.data.spot_blend = 300.0, 1.0, 0.0
    spot.data.shadow_soft_size = 0.0
    spot.location = (0.3, 0.2, 1.0)
    bpy.context.scene.collection.objects.link(spot)
    props = bpy.context.scene.visibake
    props.mode, props.directions, props.bounces, props.use_cache = "vertex", 16, 0, False
    props.refine_vertex_objects = True
    props.bake_all = True
    return plane, limit


def test_rebaking_a_refined_file_makes_no_copy_of_the_copy(visibake, clean_scene):
    plane, limit = _coarse_plane_under_a_spot(visibake)
    counts = []
    for _ in range(3):
        assert bpy.ops.visibake.bake() == {"FINISHED"}
        copies = [o for o in bpy.data.objects if o.get("visibake_refined_from")]
        assert len(copies) == 1, [o.name for o in bpy.data.objects]
        [copy] = copies
        assert copy["visibake_refined_from"] == plane.name and plane.hide_render and not copy.hide_render
        assert "(VisiBake refined) (VisiBake refined)" not in copy.name + copy.data.name
        assert len(copy.name.encode()) <= limit and len(copy.data.name.encode()) <= limit
        # Named after the original, hashed instead of cut by Blender, the same on every re-bake.
        assert copy.name == copy.data.name == visibake.operators.adapter.refine.refined_name(plane.name)
        assert not [m.name for m in bpy.data.meshes if m.users == 0]
        counts.append(len(copy.data.vertices))
    assert counts[0] > len(plane.data.vertices)
    assert len(bpy.data.meshes) == 2  # the user's and the one refined copy's


def test_a_failed_rebake_of_a_refined_copy_gives_it_back_its_mesh(visibake, clean_scene):
    plane, _ = _coarse_plane_under_a_spot(visibake)
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    [copy] = [o for o in bpy.data.objects if o.get("visibake_refined_from")]
    mesh, vertices, meshes = copy.data.name, len(copy.data.vertices), sorted(bpy.data.meshes.keys())
    calls = []

    def cancel_in_the_refined_bake(stage, fraction):
        calls.append(stage)
        if calls.count("layout") > 1:
            raise visibake.core.errors.Cancelled()

    with pytest.raises(visibake.core.errors.Cancelled):
        visibake.operators.adapter.job.run_bake(bpy.context, [copy], progress=cancel_in_the_refined_bake, refine=True)
    assert calls.count("layout") == 2  # it was refined again, then cancelled
    assert copy.data.name == mesh and len(copy.data.vertices) == vertices
    assert sorted(bpy.data.meshes.keys()) == meshes and "visibake_refined_previous_mesh" not in copy
    assert "VB_lighting" in copy.data.color_attributes and plane.hide_render


def test_rolling_back_a_refined_bake_removes_its_copy(visibake, clean_scene):
    plane, _ = _coarse_plane_under_a_spot(visibake)
    objects, meshes = set(bpy.data.objects.keys()), set(bpy.data.meshes.keys())
    outcome = visibake.operators.adapter.job.run_bake(bpy.context, [plane], refine=True)
    assert outcome.report["refined"] and not plane.visible_get()
    outcome.rollback()
    assert set(bpy.data.objects.keys()) == objects and set(bpy.data.meshes.keys()) == meshes
    assert plane.visible_get() and not plane.hide_render
