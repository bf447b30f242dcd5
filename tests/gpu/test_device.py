"""Device choice end to end: the same bake on the GPU and in numpy, and what auto picks."""
import json
import sys

import bpy

import numpy as np
import OpenEXR
import pytest

from bpy_scenes import black_world, cube, grid, material, mesh_object, point, sun, uv_sphere


@pytest.fixture
def scene_file(clean_scene, tmp_path):
    black_world()
    mesh_object("Ground", grid(1.0), material("White", (0.8, 0.8, 0.8)))
    mesh_object("Block", cube(0.5), material("Red", (0.7, 0.2, 0.1)), location=(0, 0, 0.5), uv_map=None)
    mesh_object("Glow", cube(0.1), material("Glow", (0.5, 0.5, 0.5), emission=(1.0, 0.8, 0.5), strength=20.0),
                location=(0.6, -0.6, 0.2), uv_map=None)
    ball = mesh_object("Ball", uv_sphere(0.25, 24, 12), material("Ivory", (0.7, 0.7, 0.6)),
                       location=(-0.5, -0.4, 0.3), uv_map=None)
    ball.visibake.mode = "vertex"  # its samples are vertices: the gathers look it up by triangle
    sun(3.0, tilt_degrees=30.0)
    point(60.0, (-0.5, 0.4, 1.0), name="Lamp")
    path = tmp_path / "scene.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path), copy=True)
    return path


def _bake(visibake, path, out, device, *extra):
    report = out / "report.json"
    status = visibake.cli.main(["bake", str(path), "--out", str(out), "--report", str(report), "--device", device,
                                "--directions", "64", "--bounces", "2", "--resolution", "32", "--no-cache",
                                "--light-groups", "--passes", "lighting,indirect", "--no-progress", *extra])
    assert status == 0
    return json.loads(report.read_text())


def _exr(path):
    with OpenEXR.File(str(path)) as exr:
        return exr.channels()["RGBA"].pixels


def _ball_colors():
    attribute = bpy.data.objects["Ball"].data.color_attributes["VB_lighting"]
    values = np.empty(len(attribute.data) * 4, np.float32)
    attribute.data.foreach_get("color", values)
    return values.reshape(-1, 4)


def test_gpu_and_cpu_bakes_agree(visibake, gpu_shaders, scene_file, tmp_path):
    gpu_report = _bake(visibake, scene_file, tmp_path / "gpu", "gpu")
    gpu_ball = _ball_colors()
    cpu_report = _bake(visibake, scene_file, tmp_path / "cpu", "cpu")
    cpu_ball = _ball_colors()
    np.testing.assert_allclose(gpu_ball, cpu_ball, rtol=1e-4, atol=1e-6)
    assert cpu_ball[:, :3].max() > 0
    assert gpu_report["device"]["used"] == "gpu" and gpu_report["device"]["renderer"]
    assert cpu_report["device"]["used"] == "cpu"
    gathers = [p for p in gpu_report["passes"] if p["pass"].startswith("gather")]
    assert len(gathers) == 3 and all(p["device"] == "gpu" for p in gathers)  # emission + 2 bounces
    assert all(p["device"] == "cpu" for p in cpu_report["passes"])
    for kind in ("accumulation", "direct light", "gutter dilation"):
        passes = [p for p in gpu_report["passes"] if p["pass"].startswith(kind)]
        assert passes and all(p["device"] == "gpu" for p in passes), kind
    files = sorted(f.relative_to(tmp_path / "gpu") for f in (tmp_path / "gpu").rglob("*.exr"))
    assert len(files) >= 8  # two passes, combined and per group (Sun, Lamp, Glow), for every object
    for name in files:
        ours, twin = _exr(tmp_path / "gpu" / name), _exr(tmp_path / "cpu" / name)
        assert np.all(np.isfinite(ours))
        # float32 sums in another order: see tests/gpu/test_gather_twin.py
        np.testing.assert_allclose(ours, twin, rtol=1e-4, atol=1e-6, err_msg=str(name))


def test_auto_picks_numpy_on_a_software_renderer(visibake, gpu_shaders, scene_file, tmp_path, monkeypatch):
    """Where a GPU device file is present, auto asks the context's renderer."""
    info = gpu_shaders.runtime.device_info()
    monkeypatch.setattr(gpu_shaders.runtime, "gpu_device_files", lambda: ["/dev/dri/renderD128"])
    report = _bake(visibake, scene_file, tmp_path / "auto", "auto")
    expected = "cpu" if info.software else "gpu"
    assert report["device"]["used"] == expected
    assert info.renderer in report["device"]["reason"]


def test_auto_picks_the_cpu_without_a_context_where_linux_has_no_gpu_device(visibake, gpu_shaders, scene_file,
                                                                             tmp_path, monkeypatch):
    """No GPU device file on Linux: auto takes the CPU kernels without making a context (which
    held 96 MiB to the bake's end on the demo) and says why; gpu still makes one."""
    runtime = gpu_shaders.runtime
    monkeypatch.setattr(runtime, "gpu_device_files", lambda: [])

    def no_context():
        raise AssertionError("auto made a GPU context")

    monkeypatch.setattr(runtime, "device_info", no_context)
    report = _bake(visibake, scene_file, tmp_path / "auto", "auto")
    assert report["device"]["used"] == "cpu" and "renderer" not in report["device"]
    assert "no GPU device on this machine" in report["device"]["reason"]
    assert all(p["device"] == "cpu" for p in report["passes"])
    with pytest.raises(AssertionError, match="made a GPU context"):
        runtime.choose_device("gpu")


def test_gpu_device_files_are_listed_on_linux_only(gpu_shaders, monkeypatch):
    runtime = gpu_shaders.runtime
    found = runtime.gpu_device_files()
    if sys.platform.startswith("linux"):
        assert isinstance(found, list) and all(path.startswith("/dev/") for path in found)
    monkeypatch.setattr(runtime.sys, "platform", "darwin")
    assert runtime.gpu_device_files() is None
