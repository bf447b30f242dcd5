// SPDX-License-Identifier: GPL-3.0-or-later
//
// VisiBake on Flamenco: a bake split into steps and parts that exchange files in a job
// folder on the farm's shared storage (core/distributed/farm.py). Put this file in the
// Manager's scripts/ folder; the Blender add-on of Flamenco then offers "VisiBake Bake".
//
// The tasks, in dependency order:
//   step-00             blender -b FILE -c visibake farm-step FILE --job DIR --parts P --out OUT ...
//   part-00-0 .. P-1    blender -b FILE -c visibake farm-part --job DIR --part I     (after step-00)
//   step-01             (after every part-00-*)   ... up to step-S
//   check               blender -b FILE -c visibake farm-check --job DIR          (after step-S)
// Each step runs the bake again from the start and gets one call further (the parts'
// answers are in the job folder); the step that finishes writes the results, and later
// steps and parts have nothing to do. "check" fails the job if the bake needed more steps.
//
// Written in ES5 (var, function), which every JavaScript engine Flamenco has used runs.

var JOB_TYPE = {
    label: "VisiBake Bake",
    description: "Bake lighting with VisiBake, split into parts over the farm's workers",
    settings: [
        {key: "blendfile", type: "string", required: true, visible: "web",
         description: "The .blend to bake, on the shared storage"},
        {key: "job_folder", type: "string", subtype: "dir_path", required: true,
         eval: "str(Path(abspath('//visibake_jobs'), jobname))",
         description: "Where the steps exchange files (one folder per job, on the shared storage)"},
        {key: "output_folder", type: "string", subtype: "dir_path", required: true,
         eval: "str(Path(abspath(bpy.context.scene.visibake.output_dir or '//visibake')))",
         description: "Where the last step writes <object>/<pass>.exr"},
        {key: "parts", type: "int32", default: 4, propargs: {min: 1, max: 256},
         description: "Ranges of texels: one task per range in every step"},
        {key: "steps", type: "int32", default: 16, propargs: {min: 2, max: 200},
         eval: "bpy.context.scene.visibake.bounces + bpy.context.scene.visibake.interleave ** 2 + 9 + sum(o.type == 'LIGHT' for o in bpy.context.scene.objects)",
         description: "Steps planned; the bake asks for about bounces + rotations + lamps + 9 (unused ones do nothing)"},
        {key: "bake_args", type: "string", default: "",
         description: "More options of visibake bake, e.g. --directions 256 --bounces 3"}
    ]
};

function visibakeCommand(settings, words) {
    return author.Command("blender-render", {
        exe: "{blender}",
        exeArgs: "{blenderArgs}",
        argsBefore: [],
        blendfile: settings.blendfile,
        args: ["-c", "visibake"].concat(words)
    });
}

function splitWords(text) {
    var words = [];
    var parts = (text || "").split(" ");
    for (var i = 0; i < parts.length; i++) {
        if (parts[i].length > 0) {
            words.push(parts[i]);
        }
    }
    return words;
}

function pad(number) {
    return number < 10 ? "0" + number : "" + number;
}

function compileJob(job) {
    var settings = job.settings;
    var parts = settings.parts;
    var steps = settings.steps;
    if (!(parts >= 1) || !(steps >= 1)) {
        throw "VisiBake Bake: parts and steps must be at least 1";
    }
    var stepWords = ["farm-step", settings.blendfile, "--job", settings.job_folder, "--parts", "" + parts,
                     "--out", settings.output_folder].concat(splitWords(settings.bake_args));
    var waiting = [];
    for (var step = 0; step <= steps; step++) {
        var driver = author.Task("step-" + pad(step), "blender");
        driver.addCommand(visibakeCommand(settings, stepWords));
        for (var w = 0; w < waiting.length; w++) {
            driver.addDependency(waiting[w]);
        }
        job.addTask(driver);
        if (step === steps) {
            waiting = [driver];
            break;
        }
        waiting = [];
        for (var index = 0; index < parts; index++) {
            var part = author.Task("part-" + pad(step) + "-" + index, "blender");
            part.addCommand(visibakeCommand(settings, ["farm-part", "--job", settings.job_folder, "--part",
                                                       "" + index]));
            part.addDependency(driver);
            job.addTask(part);
            waiting.push(part);
        }
    }
    var check = author.Task("check", "blender");
    check.addCommand(visibakeCommand(settings, ["farm-check", "--job", settings.job_folder]));
    check.addDependency(waiting[0]);
    job.addTask(check);
}
