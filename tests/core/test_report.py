"""The bake report: its record reads and writes today's JSON exactly, and its three texts."""
import json

import numpy as np
import pytest

from core.outputs.report import Report
from core.outputs.summary import panel_lines, summary_line, summary_lines
from core.pipeline.prepare import prepare
from core.pipeline.relight import bake, relight, relight_many
from core.scene import Light, Material, Mesh, Scene, World
from core.settings import BakeSettings
from core.visibility.cache import VisibilityCache
from core_scenes import quad_mesh

SUN = Light("Sun", "SUN", np.ones(3), 3.0, direction=np.array([0.3, 0.1, -1.0]) / np.linalg.norm([0.3, 0.1, 1.0]))
SETTINGS = BakeSettings(directions=32, bounces=1, seed=1)


def _ground(**options):
    return quad_mesh("Ground", [(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)], resolution=16, **options)


def _roof(output=False):
    return quad_mesh("Roof", [(-.3, -.3, .6), (.3, -.3, .6), (.3, .3, .6), (-.3, .3, .6)], resolution=8, output=output)


def _flipped():
    """A quad facing down under the sun: rays from the ground hit its back."""
    return quad_mesh("Flip", [(-.3, -.3, .3), (-.3, .3, .3), (.3, .3, .3), (.3, -.3, .3)], resolution=8)


def _vertex_grid(segments=4, size=2.0):
    """A vertex-mode grid facing +z (the tessellation check reports on it)."""
    coords = np.linspace(-size / 2, size / 2, segments + 1)
    xs, ys = np.meshgrid(coords, coords)
    positions = np.stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)], axis=1)
    triangles = []
    for row in range(segments):
        for col in range(segments):
            a = row * (segments + 1) + col
            triangles += [[a, a + 1, a + segments + 2], [a, a + segments + 2, a + segments + 1]]
    triangles = np.array(triangles, np.int32)
    uv = (positions[:, :2] / size + 0.5).astype(np.float32)
    return Mesh(name="V", positions=positions, triangles=triangles,
                corner_normals=np.tile(np.array([0, 0, 1], np.float32), (len(triangles), 3, 1)),
                material_index=np.zeros(len(triangles), np.int32), materials=[Material()],
                uv_maps={"UVMap": uv[triangles]}, bake_uv_map="UVMap", resolution=(16, 16), mode="vertex",
                vertex_count=len(positions), corner_loops=np.arange(3 * len(triangles)).reshape(-1, 3),
                loop_count=3 * len(triangles))


def _same_json(a: dict, b: dict) -> None:
    # json.dumps keeps key order, so this also checks the order of every level.
    assert json.dumps(a, default=float) == json.dumps(b, default=float)


def _reports(tmp_path) -> list[dict]:
    cache = VisibilityCache(str(tmp_path), "report")
    scene = Scene([_ground(), _roof(), _flipped()], [SUN])
    miss = relight(prepare(scene, SETTINGS, cache=cache), scene.lights, scene.world).report
    hit = relight(prepare(scene, SETTINGS, cache=cache), scene.lights, scene.world).report
    vertex = bake(Scene([_vertex_grid(), _roof()], [SUN]), SETTINGS).report
    prepared = prepare(Scene([_ground(), _roof()], [SUN]), SETTINGS, table_needed=True)
    many = [r.report for r in relight_many(prepared, [([SUN], World()), ([], World())])]
    return [miss, hit, vertex, *many]


def test_the_record_reads_and_writes_the_core_s_reports_exactly(tmp_path):
    reports = _reports(tmp_path)
    miss, hit, vertex = reports[:3]
    assert miss["cache"]["state"] == "miss" and hit["cache"]["state"] == "hit"
    assert hit["cache"]["lighting_reused"] == ["all"]
    assert "buried_texels" in miss["objects"][0]  # the flipped quad's back is hit
    assert "under_tessellated_triangles" in vertex["objects"][0]
    for report in reports:
        _same_json(Report.from_dict(report).to_dict(), report)
        assert list(report)[:3] == ["settings", "objects", "stage_seconds"] and list(report)[-1] == "passes"


def _job_report() -> dict:
    """A report as the Blender job finishes it (every optional field set)."""
    return {
        "settings": {"directions": 64, "bounces": 2, "shadows": "exact", "passes": ["lighting", "ao"]},
        "objects": [
            {"name": "Ground", "output": True, "uv_map": "UVMap", "resolution": [32, 16], "texels": 500,
             "triangles": 2, "buried_texels": 3,
             "estimated_error": {"total": 0.023, "lamps": 0.004, "gathered": 0.0227},
             "mode": "atlas", "layout_reason": "its UV map",
             "uv_map_created": False},
            {"name": "Leaf", "output": True, "uv_map": "", "resolution": [12, 1], "texels": 12, "triangles": 4,
             "under_tessellated_triangles": 1, "under_tessellated_area_share": 0.25, "mode": "vertex",
             "layout_reason": "vertex mode was asked for", "uv_map_created": False},
            {"name": "Wall", "output": False, "uv_map": "UVMap", "resolution": [8, 8], "texels": 40,
             "triangles": 2},
        ],
        "stage_seconds": {"layout": 0.01, "visibility": 1.234, "write": 0.5},
        "lightings_transported_together": 2,
        "rays": {"visibility_cast": 12345, "visibility_in_table": 12345, "visibility_skipped_below_horizon": 678,
                 "backface_hits": 9, "shadow_rays": 90, "emitter_rays": 0},
        "light_groups": [], "emitters_sampled": [], "gathers": 3, "table_bytes": 1000,
        "cache": {"state": "miss", "path": "/c/t.npz", "message": "no cached visibility", "changed_objects": [],
                  "bytes_on_disk": 3 * 2**20, "load_seconds": 0.0, "save_seconds": 0.1,
                  "lighting_reused": ["Key"], "abandoned_writes_removed": 0, "estimated_bytes": 3 * 2**20 - 4096,
                  "not_cached": "", "evicted": [{"slot": "/c/old-0123456789ab", "bytes": 2**20}]},
        "skipped": ["bounce gathers: bounces = 0"], "warnings": ["object 'Leaf': coarse"],
        "estimated_error": {"total": 0.021, "lamps": 0.004, "gathered": 0.0206, "unestimated_share": 0.0},
        "kernels": {"backend": "numba", "version": "0.68.1", "load_seconds": 9.2, "compiled": True,
                    "cache_dir": "/k", "reason": None},
        "passes": [{"pass": "gather 1", "device": "cpu", "seconds": 0.25}],
        "total_seconds": 2.345, "peak_memory_bytes": 200 * 2**20, "files": ["/o/a.exr", "/o/b.exr"],
        "blender_version": "5.0.1", "lights": ["Sun"], "relight_only": False,
        "device": {"requested": "auto", "used": "gpu", "reason": "a GPU was found", "backend": "OPENGL",
                   "renderer": "NVIDIA", "vendor": "NVIDIA", "version": "4.6", "software": False,
                   "gpu_memory_budget_mib": 1024},
        "setups": [{"name": "noon", "lights": ["Sun"], "stage_seconds": {"transport": 0.5}, "gathers": 3,
                    "shadow_rays": 90, "lighting_reused": ["Key"]}],
        "refined": [{"object": "Leaf", "copy": "Leaf refined", "coarse_triangles": 1, "vertices": [6, 9]}],
    }


def test_the_record_reads_and_writes_a_finished_job_s_report_exactly():
    report = _job_report()
    _same_json(Report.from_dict(report).to_dict(), report)


def test_a_field_of_another_schema_is_refused_and_a_missing_one_takes_its_default():
    with pytest.raises(ValueError, match="unknown report fields"):
        Report.from_dict({**_job_report(), "colour": "blue"})
    with pytest.raises(ValueError, match="unknown report fields"):
        Report.from_dict({"rays": {"visibility_cast": 1, "gamma_rays": 2}})
    old = Report.from_dict({"total_seconds": 1.0})  # a report from an older version, kept in a .blend
    assert old.rays.visibility_cast == 0 and old.cache_state == "off" and old.device is None


def test_the_terminal_summary():
    assert summary_lines(_job_report()) == [
        "VisiBake bake finished",
        "  settings: 64 directions, 2 bounces, shadows exact, passes lighting,ao",
        "  Ground           baked    32x16      500 texels  UV map UVMap",
        "  Leaf             baked    vertex         12 samples (vertex mode was asked for)",
        "  Wall             occluder 8x8       40 texels  UV map UVMap",
        "  rays: 12345 traced, 678 skipped below the horizon, 90 shadow rays",
        "  estimated error 2.1% per texel (lamps 0.4%, gathered 2.1%); per object: Ground 2.3%",
        "  device: gpu (a GPU was found); OPENGL, NVIDIA",
        "  CPU lookups: numba 0.68.1 kernels, compiled on first use in 9.2 s",
        "  pass: gather 1 on cpu: 0.250 s",
        "  cache: miss (no cached visibility), 3.0 MiB at /c/t.npz",
        "  cache limit: removed 1 least recently used cached tables (1.0 MiB) to make room",
        "  setup noon: 1 lights, 3 gathers, reused Key",
        "  seconds: layout 0.01, visibility 1.23, write 0.50; total 2.35",
        "  peak memory: 200 MiB",
        "  skipped: bounce gathers: bounces = 0",
        "  warning: object 'Leaf': coarse",
        "  files: 2 written",
    ]


def test_the_one_line_summary():
    report = _job_report()
    assert summary_line(report) == ("VisiBake: baked 2 object(s), 512 texels, 12345 visibility rays, in 2.3 s")
    report["relight_only"] = True
    report["cache"]["state"] = "hit"
    assert summary_line(report) == "VisiBake: relit 2 object(s), 512 texels, visibility from the cache, in 2.3 s"
    report["cache"]["state"] = "updated"
    assert "visibility updated for changed objects" in summary_line(report)
    # Not cached: traced by row ranges (a split bake), or not traced at all.
    report["cache"]["state"] = "unused"
    assert "12345 visibility rays" in summary_line(report)
    report["rays"]["visibility_cast"] = 0
    assert "no visibility needed" in summary_line(report)


def test_the_panel_lines_share_the_terminal_s_phrases():
    report = _job_report()
    lines = panel_lines(report)
    assert lines == [
        ("2.3 s in total", "TIME"),
        ("layout: 0.01 s", "BLANK1"), ("visibility: 1.23 s", "BLANK1"), ("write: 0.50 s", "BLANK1"),
        ("rays: 12345 traced, 678 skipped below the horizon, 90 shadow rays", "LIGHT_SUN"),
        ("estimated error 2.1% per texel (lamps 0.4%, gathered 2.1%)", "INFO"),
        ("cache: miss (no cached visibility)", "FILE_CACHE"),
        ("device: gpu (a GPU was found); OPENGL, NVIDIA", "MEMORY"),
        ("CPU lookups: numba 0.68.1 kernels, compiled on first use in 9.2 s", "MEMORY"),
        ("skipped: bounce gathers: bounces = 0", "FORWARD"),
        ("object 'Leaf': coarse", "ERROR"),
    ]
    terminal = summary_lines(report)
    for text, icon in lines:
        if icon in ("LIGHT_SUN", "MEMORY", "FORWARD"):
            assert "  " + text in terminal
    assert terminal[10].startswith("  " + lines[6][0])  # the terminal adds the size and place
    assert terminal[6].startswith("  " + lines[5][0])  # and the objects' estimates


def test_the_panel_reads_a_report_of_another_version_and_shows_what_it_knows():
    older = {"total_seconds": 1.25, "stage_seconds": {"visibility": 1.0}}
    expected = [("1.2 s in total", "TIME"), ("visibility: 1.00 s", "BLANK1"),
                ("rays: 0 traced, 0 skipped below the horizon, 0 shadow rays", "LIGHT_SUN")]
    assert panel_lines(older) == expected
    newer = {**older, "colour": "blue", "rays": {"visibility_cast": 0, "gamma_rays": 2}}
    assert panel_lines(newer) == expected
