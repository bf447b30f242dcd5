"""The Flamenco job type (issue 20): flamenco/visibake-bake.js compiles in an ES5 engine
(Duktape) and makes the task list of a farm bake: steps, a part task per range after each
step, each step after the parts before it, and a last check. The same list is executed end to
end in tests/blender/test_cli_cluster.py."""
import pytest
from flamenco_support import compile_job

SETTINGS = {"blendfile": "/farm/shots/room.blend", "job_folder": "/farm/jobs/visibake/room-1",
            "output_folder": "/farm/out/room", "parts": 3, "steps": 4, "bake_args": " --directions 256  --bounces 3 "}


def test_the_job_type_declares_its_settings():
    job_type = compile_job(SETTINGS)["job_type"]
    assert job_type["label"] == "VisiBake Bake"
    keys = [setting["key"] for setting in job_type["settings"]]
    assert keys == ["blendfile", "job_folder", "output_folder", "parts", "steps", "bake_args"]


def test_steps_parts_and_check_depend_on_each_other_in_order():
    tasks = compile_job(SETTINGS)["tasks"]
    names = [task["name"] for task in tasks]
    assert names == ["step-00", "part-00-0", "part-00-1", "part-00-2", "step-01", "part-01-0", "part-01-1",
                     "part-01-2", "step-02", "part-02-0", "part-02-1", "part-02-2", "step-03", "part-03-0",
                     "part-03-1", "part-03-2", "step-04", "check"]
    by_name = {task["name"]: task for task in tasks}
    assert by_name["step-00"]["depends"] == []
    assert by_name["part-01-2"]["depends"] == ["step-01"]
    assert by_name["step-02"]["depends"] == ["part-01-0", "part-01-1", "part-01-2"]
    assert by_name["check"]["depends"] == ["step-04"]
    for task in tasks:  # every task after the ones it depends on: the list is in an order a farm may run
        assert all(names.index(other) < names.index(task["name"]) for other in task["depends"])
        assert task["type"] == "blender" and len(task["commands"]) == 1


def test_each_task_runs_the_visibake_command_with_its_arguments():
    by_name = {task["name"]: task for task in compile_job(SETTINGS)["tasks"]}
    step = by_name["step-03"]["commands"][0]
    assert step["name"] == "blender-render"
    assert step["parameters"]["exe"] == "{blender}" and step["parameters"]["blendfile"] == SETTINGS["blendfile"]
    assert step["parameters"]["args"] == ["-c", "visibake", "farm-step", SETTINGS["blendfile"], "--job",
                                          SETTINGS["job_folder"], "--parts", "3", "--out", SETTINGS["output_folder"],
                                          "--directions", "256", "--bounces", "3"]
    assert by_name["part-02-1"]["commands"][0]["parameters"]["args"] == [
        "-c", "visibake", "farm-part", "--job", SETTINGS["job_folder"], "--part", "1"]
    assert by_name["check"]["commands"][0]["parameters"]["args"] == [
        "-c", "visibake", "farm-check", "--job", SETTINGS["job_folder"]]


def test_parts_or_steps_below_one_are_refused():
    import dukpy

    with pytest.raises(dukpy.JSRuntimeError, match="at least 1"):
        compile_job(dict(SETTINGS, parts=0))
