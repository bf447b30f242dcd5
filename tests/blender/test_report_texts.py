"""A real bake's report: its record reads the stored JSON exactly, and the operator, the
command line and the panel print it through the one formatter."""
import json

import bpy

from bpy_scenes import ground_block_lamp


def _scene(tmp_path):
    ground_block_lamp()
    bpy.context.scene.visibake.cache_dir = str(tmp_path / "cache")


def test_the_operator_s_report_reads_back_exactly_and_prints_through_the_formatter(visibake, clean_scene, tmp_path):
    records, texts = visibake.core.outputs.report, visibake.core.outputs.summary
    _scene(tmp_path)
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    stored = bpy.context.scene["visibake_report"]
    report = json.loads(stored)
    assert json.dumps(records.Report.from_dict(report).to_dict(), default=float) == stored
    assert {"total_seconds", "files", "device", "blender_version"} <= set(report)
    assert bpy.context.scene["visibake_last_report"] == texts.summary_line(report)
    assert visibake.panels.main.report_lines(report) == texts.panel_lines(report)


def test_the_command_line_prints_the_summary_of_the_report_it_writes(visibake, clean_scene, tmp_path, capsys):
    _scene(tmp_path)
    path = tmp_path / "scene.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path), copy=True)
    report_path = tmp_path / "report.json"
    assert visibake.cli.main(["bake", str(path), "--report", str(report_path), "--no-progress",
                              "--cache-dir", str(tmp_path / "cache")]) == 0
    report = json.loads(report_path.read_text())
    printed = capsys.readouterr().out.strip().splitlines()
    summary = visibake.core.outputs.summary.summary_lines(report)
    assert printed[-len(summary):] == summary
    assert summary[0] == "VisiBake bake finished" and any(line.startswith("  cache: miss") for line in summary)
