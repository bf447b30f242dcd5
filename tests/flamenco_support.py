"""The Flamenco job type (flamenco/visibake-bake.js) compiled by Duktape (dukpy), with an
``author`` and a ``job`` that record what Flamenco's would: the task list a Manager would make."""
import json
from pathlib import Path

JOB_TYPE = Path(__file__).resolve().parents[1] / "flamenco" / "visibake-bake.js"

_RECORDER = """
var author = {
    Task: function (name, type) {
        var task = {name: name, type: type, commands: [], depends: []};
        task.addCommand = function (command) { task.commands.push(command); };
        task.addDependency = function (other) { task.depends.push(other.name); };
        return task;
    },
    Command: function (name, parameters) { return {name: name, parameters: parameters}; }
};
var compiled = [];
compileJob({settings: dukpy.settings, addTask: function (task) { compiled.push(task); }});
JSON.stringify({job_type: JOB_TYPE, tasks: compiled});
"""


def compile_job(settings: dict) -> dict:
    """{"job_type": JOB_TYPE, "tasks": [{name, type, commands: [{name, parameters}], depends: [names]}]}
    in the order compileJob added them."""
    import dukpy

    return json.loads(dukpy.evaljs([JOB_TYPE.read_text(encoding="utf-8"), _RECORDER], settings=settings))
