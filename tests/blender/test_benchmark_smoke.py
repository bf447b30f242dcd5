"""The benchmark's smoke profile runs end to end, so the benchmark code cannot rot.

Only shapes and sanity are checked here; timings are never asserted in tests.
"""
import csv
import json
import math
import os
import subprocess
import sys

from blender_support import REPO_ROOT


def test_smoke_profile_writes_csv_plot_and_summary(tmp_path):
    out = tmp_path / "bench"
    result = subprocess.run(
        [sys.executable, str(REPO_ROOT / "benchmarks" / "run.py"), "--profile", "smoke", "--out", str(out),
         "--cache", str(tmp_path / "cache")],
        capture_output=True, text=True, timeout=900,
        env={**os.environ, "BLENDER_USER_RESOURCES": str(tmp_path / "user")})
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    rows = list(csv.DictReader(open(out / "sun_occluders.csv")))
    methods = {row["method"] for row in rows}
    assert methods == {"visibake", "cycles"}
    assert len([r for r in rows if r["method"] == "visibake"]) == 3  # directions 8 and 16, target 0.5
    targeted = next(r for r in rows if r["target_error"])
    # The smoke scene's pilot meets so loose a target: it is the bake, with its own estimate beside it.
    assert float(targeted["target_error"]) == 0.5 and int(targeted["directions"]) == 64
    assert 0 < float(targeted["estimated_error"]) < 0.5
    assert len([r for r in rows if r["method"] == "cycles"]) == 2  # 1 and 4 samples
    for row in rows:
        error = float(row["relative_rmse"])
        assert math.isfinite(error) and error >= 0
        assert float(row["seconds"]) > 0
        assert json.loads(row["stage_seconds"])
    assert (out / "sun_occluders.png").stat().st_size > 1000
    summary = json.loads((out / "summary.json").read_text())
    assert summary["profile"] == "smoke" and summary["machine"]["cpus"] >= 1
    assert [r["setups"] for r in summary["relight"]] == [1, 2]
    assert summary["limits"][0]["embree_rays_per_second"] > 0
    assert "| sun_occluders" in (out / "summary.md").read_text()
    assert "| target 0.5: 64 |" in (out / "summary.md").read_text()
    vertex_rows = list(csv.DictReader(open(out / "vertex.csv")))
    ours = [r for r in vertex_rows if r["method"] == "visibake"]
    assert {r["lookup"] for r in ours} == {"interpolate", "nearest"} and len(ours) == 4
    assert all(math.isfinite(float(r["relative_rmse"])) for r in vertex_rows)
    assert "Vertex-table mode" in (out / "summary.md").read_text()
    limits = summary["limits"][0]
    assert limits["numpy_gather_lookups_per_second"] > 0
    # A second run finds the reference in the cache instead of baking it again.
    again = subprocess.run(
        [sys.executable, str(REPO_ROOT / "benchmarks" / "run.py"), "--profile", "smoke", "--out", str(out / "again"),
         "--cache", str(tmp_path / "cache")],
        capture_output=True, text=True, timeout=900,
        env={**os.environ, "BLENDER_USER_RESOURCES": str(tmp_path / "user")})
    assert again.returncode == 0
    assert "(cached)" in again.stdout


def test_accuracy_benchmark_writes_errors_with_the_reference_noise_and_a_plot(tmp_path):
    out = tmp_path / "accuracy"
    process = subprocess.run(
        [sys.executable, str(REPO_ROOT / "benchmarks" / "accuracy.py"), "--size", "smoke", "--scenes", "sun_occluders",
         "--resolution", "32", "--directions", "8", "--reference-samples", "8", "--variants", "texel centres",
         "+ interleaved rotations", "--out", str(out), "--cache", str(tmp_path / "cache")],
        capture_output=True, text=True, timeout=600, cwd=str(REPO_ROOT))
    assert process.returncode == 0, process.stderr[-2000:]
    result = json.loads((out / "accuracy.json").read_text())
    runs = result["scenes"]["sun_occluders"]["runs"]
    assert [r["variant"] for r in runs] == ["texel centres", "+ interleaved rotations"]
    for run in runs:
        assert 0 < run["relative_rmse"] < 10 and 0 <= run["block_rmse_denoised"] <= run["block_rmse"]
    assert result["scenes"]["sun_occluders"]["texel_noise"] > 0
    assert (out / "sun_occluders.png").stat().st_size > 1000
    assert "| variant | N |" in (out / "summary.md").read_text()


def test_the_accuracy_benchmark_s_last_variant_is_the_product_s_default():
    """Its figures are quoted as the default's: a default changed without it (interleave 3 -> 4,
    speed part 16) went unmeasured until part 18."""
    import importlib.util

    from core.settings import BakeSettings

    spec = importlib.util.spec_from_file_location("accuracy_benchmark", REPO_ROOT / "benchmarks" / "accuracy.py")
    accuracy = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(accuracy)
    default = BakeSettings()
    last = list(accuracy.VARIANTS.values())[-1]
    assert {name: getattr(default, name) for name in last} == last


def test_seam_benchmark_renders_both_bakes_and_the_truth_and_measures_the_seams(tmp_path):
    out = tmp_path / "seams"
    process = subprocess.run(
        [sys.executable, str(REPO_ROOT / "benchmarks" / "seams.py"), "--resolution", "32", "--directions", "16",
         "--bounces", "1", "--width", "160", "--height", "100", "--truth-samples", "8", "--out", str(out)],
        capture_output=True, text=True, timeout=600, cwd=str(REPO_ROOT))
    assert process.returncode == 0, process.stderr[-2000:]
    result = json.loads((out / "seams.json").read_text())
    # The sphere, cylinder and torus are smooth and cut by seams; the floor is one flat quad.
    assert result["seams"]["Floor"]["seam_edges"] is None
    for name in ("Sphere", "Cylinder", "Torus"):
        before, after = result["seams"][name]["seam_disagreement"]
        assert result["seams"][name]["seam_edges"] > 0 and after < before
    assert 0 < result["seam_pixels"] < result["object_pixels"]
    for name in ("off", "on"):
        assert 0 < result["rmse"][name]["all"] < 10
    assert (out / "seams.png").stat().st_size > 1000
    assert "| seam pixels |" in (out / "summary.md").read_text()
