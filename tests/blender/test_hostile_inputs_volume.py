"""A Volume object's .vdb under damage and its densities under resampling (issue 51, items 6
and 11): a cut or byte-flipped file is bad input naming the volume and the file, and a negative
voxel is refused with its count however far ``--resolution`` averages it, through `visibake
volume` and the panel's Bake Volume."""
import importlib

import bpy

import numpy as np
import pytest
from test_volume_bake import vdb  # noqa: F401 - fixture

from blender_support import extension_module_name
from bpy_scenes import black_world, sun

SIDE = 16


def write_vdb(vdb, path, density):  # noqa: F811 - fixture
    grid = vdb.FloatGrid()
    grid.copyFromArray(np.ascontiguousarray(density, np.float32), ijk=(0, 0, 0))
    grid.name = "density"
    grid.transform = vdb.createLinearTransform((np.diag([0.05, 0.05, 0.05, 1.0])).tolist())
    vdb.write(str(path), grids=[grid])


def volume_blend(path, vdb_path, name="Cloud"):
    """A .blend with the Volume object ``name`` of ``vdb_path`` under a Principled Volume, lit by a sun."""
    bpy.ops.wm.read_homefile(use_empty=True)
    black_world()
    sun(3.0)
    volume = bpy.data.volumes.new(name)
    volume.filepath = str(vdb_path)
    obj = bpy.data.objects.new(name, volume)
    bpy.context.scene.collection.objects.link(obj)
    material = bpy.data.materials.new(name + " material")
    importlib.import_module(extension_module_name() + ".operators.adapter.compat").ensure_node_tree(material)
    tree = material.node_tree
    tree.nodes.clear()
    principled = tree.nodes.new("ShaderNodeVolumePrincipled")
    output = tree.nodes.new("ShaderNodeOutputMaterial")
    tree.links.new(principled.outputs[0], output.inputs["Volume"])
    volume.materials.append(material)
    bpy.ops.wm.save_as_mainfile(filepath=str(path), copy=True)
    return path


def _volume(visibake, blend, out, resolution=16):
    return visibake.cli.main(["volume", str(blend), "--out", str(out), "--resolution", str(resolution),
                              "--directions", "8", "--bounces", "0", "--no-progress"])


def _damage(data: bytes, how: str) -> bytes:
    """``data`` cut at a fraction of its length, or with 8 bytes flipped there (in the voxels'
    compressed blocks: a header damaged in some places hangs openvdb's own reader)."""
    kind, fraction = how.split()
    at = int(len(data) * float(fraction))
    if kind == "cut":
        return data[:at]
    damaged = bytearray(data)
    for index in range(at, at + 8):
        damaged[index] ^= 0xFF
    return bytes(damaged)


@pytest.mark.parametrize("how", ["cut 0.3", "cut 0.6", "cut 0.99", "flip 0.5", "flip 0.8"])
def test_a_damaged_vdb_exits_2_naming_the_volume_and_the_file(visibake, vdb, clean_scene, tmp_path, capfd, how):  # noqa: F811 - fixture
    path = tmp_path / "cloud.vdb"
    write_vdb(vdb, path, np.ones((SIDE, SIDE, SIDE)))
    path.write_bytes(_damage(path.read_bytes(), how))
    damaged = path.read_bytes()
    blend = volume_blend(tmp_path / "cloud.blend", path)
    out = tmp_path / "out"
    assert _volume(visibake, blend, out) == 2
    said = capfd.readouterr().err.strip().splitlines()
    assert said and "volume 'Cloud'" in said[-1] and str(path) in said[-1], said
    assert "damaged or cut short" in said[-1] or "not a readable OpenVDB file" in said[-1], said
    assert not out.exists() or not list(out.rglob("*.vdb"))
    assert path.read_bytes() == damaged  # the user's file as it was


def test_the_panel_s_bake_volume_refuses_a_cut_vdb(visibake, vdb, clean_scene, tmp_path):  # noqa: F811 - fixture
    path = tmp_path / "cloud.vdb"
    write_vdb(vdb, path, np.ones((SIDE, SIDE, SIDE)))
    path.write_bytes(_damage(path.read_bytes(), "cut 0.6"))
    bpy.ops.wm.open_mainfile(filepath=str(volume_blend(tmp_path / "cloud.blend", path)))
    props = bpy.context.scene.visibake
    props.volume_resolution, props.volume_directions, props.volume_bounces = 16, 8, 0
    props.output_dir = str(tmp_path / "panel")
    bpy.data.objects["Cloud"].select_set(True)
    objects = set(bpy.data.objects.keys())
    with pytest.raises(RuntimeError, match="volume 'Cloud': the 'density' grid of .*cloud.vdb cannot be read"):
        bpy.ops.visibake.bake_volume()  # an error report raises in scripts
    assert set(bpy.data.objects.keys()) == objects
    assert not (tmp_path / "panel").exists() or not list((tmp_path / "panel").rglob("*.vdb"))


def test_a_negative_voxel_is_refused_even_where_the_resolution_averages_it_away(visibake, vdb, clean_scene, tmp_path,  # noqa: F811 - fixture
                                                                             capfd):
    density = np.ones((SIDE, SIDE, SIDE))
    density[3, 4, 5] = -0.5  # its 2 x 2 x 2 block's mean is 0.8: positive
    path = tmp_path / "cloud.vdb"
    write_vdb(vdb, path, density)
    blend = volume_blend(tmp_path / "cloud.blend", path)
    for resolution in (SIDE, SIDE // 2):
        out = tmp_path / f"out{resolution}"
        assert _volume(visibake, blend, out, resolution) == 2, resolution
        said = capfd.readouterr().err.strip().splitlines()
        assert said and "volume 'Cloud': 1 of its density voxels are negative (lowest -0.5)" in said[-1], said
        assert not out.exists() or not list(out.rglob("*.vdb"))
    # The panel says the same.
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    props = bpy.context.scene.visibake
    props.volume_resolution, props.volume_directions, props.volume_bounces = SIDE // 2, 8, 0
    props.output_dir = str(tmp_path / "panel")
    bpy.data.objects["Cloud"].select_set(True)
    with pytest.raises(RuntimeError, match="1 of its density voxels are negative"):
        bpy.ops.visibake.bake_volume()
