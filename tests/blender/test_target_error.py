"""Bakes at a Target Error (issue 52): the directions chosen from a pilot's estimate of its own
error, remembered for the next bake and reused by Relight; the panel, the command line and the
report say what was chosen and why."""
import json

import bpy

import pytest

from bpy_scenes import black_world, cube, grid, material, mesh_object, point, sun


@pytest.fixture
def yard(clean_scene, tmp_path):
    """A saved scene with a sky: ground, a block, a sun and a point lamp."""
    black_world()
    bpy.context.scene.world.node_tree.nodes["Background"].inputs["Strength"].default_value = 0.5
    mesh_object("Ground", grid(1.0), material("White", (0.8, 0.8, 0.8)))
    mesh_object("Block", cube(0.5), material("Grey", (0.5, 0.5, 0.5)), location=(0, 0, 0.5), uv_map=None)
    sun(3.0, tilt_degrees=20.0)
    point(80.0, (0.6, 0.3, 1.2), name="Lamp")
    props = bpy.context.scene.visibake
    props.bounces, props.resolution, props.passes, props.bake_all = 1, 24, {"lighting"}, True
    path = tmp_path / "yard.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    return path


def _report():
    return json.loads(bpy.context.scene["visibake_report"])


def test_a_target_chooses_the_directions_and_relight_reuses_them(visibake, yard):
    props = bpy.context.scene.visibake
    props.directions = 32  # ignored: the target chooses
    props.target_error = 0.002
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    report = _report()
    target = report["target"]
    assert target["target_error"] == pytest.approx(0.002) and target["pilot_directions"] == 64
    # The pilot's estimate (0.41%: 0.13% lamps, 0.39% gathered) is above this tight a target:
    # a second bake at more directions.
    assert target["pilot_estimate"]["total"] > 0.002
    assert target["directions"] > 64 and report["settings"]["directions"] == target["directions"]
    assert target["predicted_error"] < target["pilot_estimate"]["total"]
    assert report["estimated_error"]["total"] < target["pilot_estimate"]["total"]
    assert target["met"] == (report["estimated_error"]["total"] <= 0.002)
    assert props.chosen_directions == target["directions"]
    # A relight keeps the chosen count: the kept preparation, no visibility ray.
    bpy.data.objects["Lamp"].data.energy = 120.0
    assert bpy.ops.visibake.relight() == {"FINISHED"}
    relit = _report()
    assert relit["settings"]["directions"] == target["directions"] and relit["rays"]["visibility_cast"] == 0
    assert relit["target"]["reason"].startswith("a relight reuses")
    # The next bake starts its pilot at the remembered count.
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    assert _report()["target"]["pilot_directions"] == target["directions"]


def test_a_target_the_pilot_meets_keeps_the_pilot(visibake, yard):
    props = bpy.context.scene.visibake
    props.target_error = 0.9
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    target = _report()["target"]
    assert target["directions"] == target["pilot_directions"] == 64
    assert "within the target" in target["reason"] and target["met"] is True
    assert props.chosen_directions == 64
    # A caller's rollback (its own later step failed) puts the remembered count back too.
    props.chosen_directions = 0
    objects = [o for o in bpy.context.scene.objects if o.type == "MESH"]
    outcome = visibake.operators.adapter.job.run_bake(bpy.context, objects, hold_replaced=True)
    assert props.chosen_directions == 64
    outcome.rollback()
    assert props.chosen_directions == 0


def test_a_target_below_the_direct_light_s_error_says_so_and_brings_the_gathered_light_to_it(visibake, yard):
    bpy.context.scene.visibake.target_error = 0.0012  # the pilot's lamps: 0.13%, its gathered light 0.39%
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    target = _report()["target"]
    assert target["directions"] > 64 and target["met"] is False
    assert "direct light's estimated error" in target["reason"] and "alone exceeds" in target["reason"]
    assert target["pilot_estimate"]["lamps"] > 0.0012 * 0.85


def test_the_command_line_takes_a_target_and_keeps_given_directions(visibake, yard, tmp_path, capfd):
    report_path = tmp_path / "report.json"
    assert visibake.cli.main(["bake", str(yard), "--target-error", "0.9", "--report", str(report_path),
                              "--no-progress", "--no-cache"]) == 0
    assert "target error 90.0%: 64 directions" in capfd.readouterr().out
    assert json.loads(report_path.read_text())["target"]["directions"] == 64
    # With --directions too, those are kept and the estimate reported against the target.
    assert visibake.cli.main(["bake", str(yard), "--target-error", "0.001", "--directions", "48", "--report",
                              str(report_path), "--no-progress", "--no-cache"]) == 0
    target = json.loads(report_path.read_text())["target"]
    assert target["directions"] == 48 and target["reason"] == "--directions was given" and target["met"] is False
    capfd.readouterr()
    assert visibake.cli.main(["bake", str(yard), "--target-error", "-0.1", "--no-progress"]) == 2
    assert "--target-error" in capfd.readouterr().err.strip().splitlines()[-1]
