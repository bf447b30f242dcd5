"""The headless command: ``blender -c visibake bake|relight|demo ...`` and ``tools/visibake.py ...``.

``bake`` traces (or reuses the cached) visibility and lights the scene; ``relight``
only re-lights from the cached visibility and refuses if the geometry changed.
Both take lighting setups (``--setups FILE.json`` or ``--sun-sweep``) and then write
one set of outputs per setup from one visibility bake.

Exit status: 0 success, 2 bad input (one line on stderr saying why), 1 failure.
"""
from __future__ import annotations

import argparse
import math
import os
import sys
import time
import traceback

import bpy

from ..core.errors import BakeRefused, Cancelled
from ..core.lights import setups as lighting_setups
from ..core.outputs import summary as report_texts
from ..core.outputs.atomic import remove_written
from ..core.outputs.destinations import FILE, FOLDER, check_destinations
from ..core.outputs.ownership import refuse_foreign
from ..core.settings import (
    APPEARANCE_SETTINGS,
    LIGHTFIELD_SETTINGS,
    PREFERENCE_SETTINGS,
    PRESETS,
    SETTINGS,
    VOLUME_SETTINGS,
    Setting,
)
from .adapter import job

EXIT_OK, EXIT_FAILURE, EXIT_BAD_INPUT = 0, 1, 2

# Every setting of the panel (scene.visibake) and the preferences, and how the command
# line sets it; tests/blender/test_parity.py checks that none is missing. The scene's
# settings travel in the .blend as well, so options only override them.
SCENE_SETTING_OPTIONS = {
    "preset": "--preset", "directions": "--directions", "bounces": "--bounces", "shadows": "--shadows",
    "target_error": "--target-error",
    "chosen_directions": None,  # what the last Target Error bake chose: state the bake keeps, not a setting
    "passes": "--passes", "resolution": "--resolution", "texel_density": "--texel-density", "mode": "--mode",
    "rotate": "--rotate", "seed": "--seed", "margin": "--margin", "use_cache": "--no-cache",
    "footprint_samples": "--footprint-samples", "interleave": "--interleave", "sharp_contacts": "--no-sharp-contacts",
    "stitch_seams": "--no-stitch-seams",
    "cache_dir": "--cache-dir", "light_groups": "--light-groups", "vertex_lookup": "--vertex-lookup",
    "refine_vertex_objects": "--refine", "output_dir": "--out",
    "bake_all": "--objects",  # the command bakes every visible mesh unless --objects names some
    "active_object_index": None,  # the selected row of the panel's list: UI state, not a setting
    # The Volumes section's settings are options of the volume command ("COMMAND OPTION").
    "volume_resolution": "volume --resolution", "volume_directions": "volume --directions",
    "volume_bounces": "volume --bounces", "volume_points": "volume --points",
    # The Materials from Micro-Geometry section's: options of the brdf command.
    "appearance_lights": "brdf --lights", "appearance_views": "brdf --views",
    "appearance_directions": "brdf --directions", "appearance_bounces": "brdf --bounces",
    "appearance_resolution": "brdf --resolution", "appearance_format": "brdf --format",
    "appearance_image_size": "btf --image-size", "appearance_image_format": "btf --format",
    # The Light Field section's: options of the lightfield command.
    "lightfield_columns": "lightfield --views", "lightfield_rows": "lightfield --views",
    "lightfield_baseline_mm": "lightfield --baseline-mm", "lightfield_focus_m": "lightfield --focus-distance-m",
    "lightfield_width": "lightfield --image-size", "lightfield_height": "lightfield --image-size",
    "lightfield_format": "lightfield --format", "lightfield_supersampling": "lightfield --supersampling",
}
# Every operator of the panel, and the command that does the same.
OPERATOR_COMMANDS = {
    "visibake.bake": "bake", "visibake.relight": "relight", "visibake.preview_add": "preview",
    "visibake.preview_remove": "preview --remove", "visibake.clear_cache": "clear-cache",
    "visibake.bake_volume": "volume", "visibake.simulate_brdf": "brdf", "visibake.simulate_btf": "btf",
    "visibake.render_lightfield": "lightfield",
}
PREFERENCE_OPTIONS = {
    "device": "--device", "threads": "--threads", "cache_dir": "--cache-dir",
    "gpu_memory_mib": None,  # a property of the machine: the command uses the preference as it is
    "cache_limit_mib": None,  # the same: the disk's room does not change per run
    # Kept between bakes of one session; a command is one bake, so there is nothing to keep.
    "resident_memory_mib": None,
    "default_preset": "--preset",  # the command takes a preset per run
    "cluster_workers": "--workers",  # the same: a command says its cluster per run
}


def _help(spec: Setting, default: bool = False, note: str = "") -> str:
    """An option's help: the setting's one help text, with its default or a note."""
    text = spec.help[:1].lower() + spec.help[1:]
    if default:
        shown = ",".join(spec.default) if spec.type is tuple else spec.default
        note = f"default {shown}" + (f"; {note}" if note else "")
    return text + (f" ({note})" if note else "")


def _setting_option(parser, option: str, spec: Setting, metavar: str | None = None, **help_options) -> None:
    """An option that sets ``spec``: its type or choices and its help come from core."""
    keywords = {"help": _help(spec, **help_options)}
    if spec.type is bool:
        keywords.update(action="store_true", default=None)
    elif spec.choices:
        keywords["choices"] = spec.values
    elif spec.type in (int, float):
        keywords["type"] = spec.type
    if metavar is not None:
        keywords["metavar"] = metavar
    parser.add_argument(option, **keywords)


def _bake_setting_options(sub) -> None:
    """The bake's settings as options of ``sub`` (bake, relight, demo, and lightfield's --bake-first)."""
    sub.add_argument("--preset", choices=tuple(name.lower() for name in PRESETS),
                     help=_help(SETTINGS["preset"], note="options below override it"))
    _setting_option(sub, "--directions", SETTINGS["directions"], "N", default=True)
    _setting_option(sub, "--target-error", SETTINGS["target_error"], "E",
                    note="with --directions as well, those directions are kept and the estimate reported")
    _setting_option(sub, "--bounces", SETTINGS["bounces"], "K", default=True)
    _setting_option(sub, "--resolution", SETTINGS["resolution"], "PX", default=True)
    _setting_option(sub, "--texel-density", SETTINGS["texel_density"], "T")
    _setting_option(sub, "--mode", SETTINGS["mode"], default=True)
    _setting_option(sub, "--shadows", SETTINGS["shadows"], default=True)
    # Parsed by _apply_settings, so that an unknown pass is refused with the choices.
    subset = f"a comma-separated subset of {','.join(SETTINGS['passes'].values)}"
    sub.add_argument("--passes", metavar="P,Q", help=_help(SETTINGS["passes"], default=True, note=subset))
    _setting_option(sub, "--rotate", SETTINGS["rotate"])
    _setting_option(sub, "--seed", SETTINGS["seed"])
    _setting_option(sub, "--margin", SETTINGS["margin"], "PX", default=True)
    _setting_option(sub, "--footprint-samples", SETTINGS["footprint_samples"], "N", default=True)
    _setting_option(sub, "--interleave", SETTINGS["interleave"], "T", default=True)
    sub.add_argument("--no-sharp-contacts", action="store_true",
                     help="read short rays' light from the target's texels (see Sharp Contacts)")
    sub.add_argument("--no-stitch-seams", action="store_true",
                     help="leave UV seams as baked, as Cycles does (see Stitch Seams)")
    _setting_option(sub, "--light-groups", SETTINGS["light_groups"])
    _setting_option(sub, "--cache-dir", SETTINGS["cache_dir"], "DIR")
    sub.add_argument("--no-cache", action="store_true", help="neither read nor write the visibility cache")
    _setting_option(sub, "--refine", SETTINGS["refine_vertex_objects"])
    _setting_option(sub, "--vertex-lookup", SETTINGS["vertex_lookup"], default=True)
    _setting_option(sub, "--device", PREFERENCE_SETTINGS["device"], note="default: the preference, else auto")
    _setting_option(sub, "--threads", PREFERENCE_SETTINGS["threads"], "N", note="default: the preference")
    sub.add_argument("--no-progress", action="store_true", help="no progress bar")


def _cluster_options(sub) -> None:
    """Where the bake's table is traced and read, by ranges of sample rows (docs/scaleout.md)."""
    group = sub.add_argument_group("on a Dask cluster (the images are the same bits as in one process)")
    group.add_argument("--workers", type=int, metavar="N",
                       help="start a local cluster of N worker processes (all cores without the GIL; at most 2 "
                            "per core)")
    group.add_argument("--scheduler", metavar="ADDRESS",
                       help="join the Dask scheduler at tcp://HOST:PORT (this machine only) or tls://HOST:PORT")
    group.add_argument("--parts", type=int, metavar="P", help="parts to split the work into: ranges of texels "
                       "for a bake, of voxels for volume, of light directions for brdf and btf, of views for "
                       "lightfield (default: 2 per worker)")
    group.add_argument("--tls-ca-file", metavar="CA.pem", help="TLS: the certificate authority of the cluster")
    group.add_argument("--tls-cert", metavar="CERT.pem", help="TLS: this client's certificate")
    group.add_argument("--tls-key", metavar="KEY.pem", help="TLS: this client's private key")
    group.add_argument("--insecure", action="store_true",
                       help="allow a plain tcp:// scheduler on another machine (anyone who reaches it can run "
                            "code on its workers)")


def _cluster(args):
    """The command's core.distributed.engine.ClusterOptions, or None for a bake in this process."""
    tls_files = (args.tls_ca_file, args.tls_cert, args.tls_key)
    if args.workers is None and args.scheduler is None:
        used = [name for name, value in (("--parts", args.parts), ("--tls-ca-file", args.tls_ca_file),
                                         ("--tls-cert", args.tls_cert), ("--tls-key", args.tls_key),
                                         ("--insecure", args.insecure or None)) if value is not None]
        if used:
            raise BakeRefused(f"{', '.join(used)}: only with --workers or --scheduler")
        return None
    from ..core.distributed.engine import ClusterOptions, TLSFiles

    tls = None
    if any(tls_files):
        if not all(tls_files):
            raise BakeRefused("TLS needs all of --tls-ca-file, --tls-cert and --tls-key")
        missing = [path for path in tls_files if not os.path.isfile(path)]
        if missing:
            raise BakeRefused(f"TLS: no such file: {', '.join(missing)}")
        tls = TLSFiles(*(os.path.abspath(path) for path in tls_files))
    options = ClusterOptions(args.workers, args.scheduler, tls, args.insecure, args.parts)
    options.validate()
    return options


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="visibake", description="Bake lighting from precomputed visibility (VisiBake).")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    bake = commands.add_parser("bake", help="bake a .blend (default: the built-in demo scene)")
    bake.add_argument("input", nargs="?", help="the .blend to bake; omitted: the built-in demo scene")
    relight = commands.add_parser(
        "relight", help="re-light a .blend from its cached visibility (fails if the geometry changed)")
    relight.add_argument("input", nargs="?", help="the .blend to relight; omitted: the built-in demo scene")
    demo = commands.add_parser("demo", help="bake the built-in demo scene with previews and a summary")
    preview = commands.add_parser(
        "preview", help="wire a baked .blend's lighting into its materials for preview (or --remove it), and save")
    preview.add_argument("input", help="the baked .blend")
    preview.add_argument("--save", metavar="OUT.blend", required=True, help="where to save the result")
    preview.add_argument("--remove", action="store_true", help="take VisiBake's preview out of every material")
    preview.add_argument("--objects", metavar="A,B", help="objects to preview (default: all visible meshes)")
    clear = commands.add_parser("clear-cache", help="delete the cached visibility of a .blend's scene")
    clear.add_argument("input", help="the .blend whose cache to delete")
    _setting_option(clear, "--cache-dir", SETTINGS["cache_dir"], "DIR")
    for sub in (bake, relight):
        sub.add_argument("--setups", metavar="SETUPS.json",
                         help="lighting setups (lights and world) to write one set of outputs each, into OUT/<setup>/")
        sub.add_argument("--sun-sweep", metavar="START:END:STEPS",
                         help="one setup per time of day, e.g. 6:18:7; the scene's sun (or a new one) follows the sky")
        sub.add_argument("--latitude", type=float, default=45.0,
                         help="latitude of the sun sweep in degrees (default 45)")
        sub.add_argument("--day", type=int, default=172, help="day of the year of the sun sweep (default 172, June 21)")
        sub.add_argument("--sun", metavar="NAME", help="the sun lamp the sweep moves (default: the scene's first sun)")
    for sub in (bake, demo):
        _cluster_options(sub)
    # A bake on a render farm (Flamenco: flamenco/visibake-bake.js), as steps exchanging files.
    step = commands.add_parser("farm-step", help="one step of a bake on a render farm: bakes as far as the job "
                               "folder's parts allow, then asks for the next parts (or writes the results)")
    step.add_argument("input", help="the .blend to bake")
    step.add_argument("--job", metavar="DIR", required=True, help="the job's folder on the farm's shared storage "
                      "(one folder per job)")
    step.add_argument("--parts", type=int, default=4, metavar="P",
                      help="ranges of texels, one part task each per step (default 4)")
    part = commands.add_parser("farm-part", help="one part of a farm bake's step: a range of texels")
    part.add_argument("input", nargs="?", help="the .blend the farm passes (not read: the job folder holds the scene)")
    part.add_argument("--job", metavar="DIR", required=True, help="the job's folder")
    part.add_argument("--part", type=int, required=True, metavar="I", help="the range to run (0 to P - 1)")
    _setting_option(part, "--threads", PREFERENCE_SETTINGS["threads"], "N", note="default: all cores")
    check = commands.add_parser("farm-check", help="exit 2 unless the farm bake in the job folder finished")
    check.add_argument("input", nargs="?", help="the .blend the farm passes (not read)")
    check.add_argument("--job", metavar="DIR", required=True, help="the job's folder")
    for sub in (bake, relight, demo, step):
        sub.add_argument("--out", metavar="DIR", help="write DIR/<object>/<pass>.exr")
        sub.add_argument("--objects", metavar="A,B",
                         help="comma-separated objects to bake (default: all visible meshes)")
        _bake_setting_options(sub)
        sub.add_argument("--save", metavar="OUT.blend", help="save the scene with its UV maps and baked images")
        sub.add_argument("--report", metavar="REPORT.json", help="write the bake report as JSON")
        sub.add_argument("--previews", action="store_true", default=None,
                         help="also write tone-mapped PNGs (<pass>.preview.ply for vertex-mode objects)")
    volume = commands.add_parser(
        "volume", help="bake the light scattered in a .blend's Volume objects into VDB grids and a baked Volume object")
    volume.add_argument("input", help="the .blend whose volumes to bake")
    volume.add_argument("--out", metavar="DIR", required=True, help="write DIR/<object>/<grid>.vdb")
    volume.add_argument("--objects", metavar="A,B",
                        help="comma-separated Volume objects or meshes with a Principled Volume (default: all visible)")
    for name, option, metavar in (("volume_resolution", "--resolution", "N"),
                                  ("volume_directions", "--directions", "N"),
                                  ("volume_bounces", "--bounces", "K"), ("volume_points", "--points", "M")):
        _setting_option(volume, option, VOLUME_SETTINGS[name], metavar, default=True)
    _setting_option(volume, "--seed", SETTINGS["seed"])
    volume.add_argument("--save", metavar="OUT.blend", help="save the scene with its baked Volume objects")
    volume.add_argument("--report", metavar="REPORT.json", help="write the bake report as JSON")
    _setting_option(volume, "--threads", PREFERENCE_SETTINGS["threads"], "N", note="default: the preference")
    _cluster_options(volume)
    _setting_option(volume, "--cache-dir", SETTINGS["cache_dir"], "DIR")
    volume.add_argument("--no-cache", action="store_true", help="neither read nor write the cached scattering tables")
    _setting_option(volume, "--device", PREFERENCE_SETTINGS["device"],
                    note="the lamps' slice sweeps; default: the preference, else auto")
    volume.add_argument("--no-progress", action="store_true", help="no progress bar")
    brdf = commands.add_parser(
        "brdf", help="simulate the BRDF of a periodic micro-geometry tile and write it as a MERL or tabulated file")
    brdf.add_argument("input", help="the .blend holding the tile")
    brdf.add_argument("--tile", metavar="NAME", required=True,
                      help="the tile: a mesh object or a collection, one period of a surface repeating in X and Y")
    brdf.add_argument("--out", metavar="FILE", required=True,
                      help="FILE.binary (MERL, isotropic) or FILE.npz (tabulated light x view values)")
    brdf.add_argument("--format", choices=("merl", "table", "bsdf"),
                      help="merl (.binary), table (.npz, the hemisphere) or bsdf (.npz, the whole sphere: lights and "
                           "views below the tile too, for see-through and translucent tiles); default: as FILE's "
                           "extension says")
    for option, metavar in (("--lights", "N"), ("--views", "N"), ("--directions", "N"), ("--bounces", "K"),
                            ("--resolution", "R")):
        _setting_option(brdf, option, APPEARANCE_SETTINGS["appearance_" + option.removeprefix("--")], metavar,
                        default=True)
    brdf.add_argument("--view-rays", type=int, default=128, metavar="R",
                      help="rays across the period per view (R x R), which measure masking")
    brdf.add_argument("--period", metavar="X,Y", help="the repeat in X and Y (default: the tile's bounding box)")
    brdf.add_argument("--phong", metavar="KS,EXP",
                      help="the paper's micro-BRDF: Lambert plus a Phong lobe of weight KS and exponent EXP on every "
                           "face (default: each material's own)")
    _setting_option(brdf, "--seed", SETTINGS["seed"])
    _setting_option(brdf, "--threads", PREFERENCE_SETTINGS["threads"], "N", note="default: the preference")
    _cluster_options(brdf)
    brdf.add_argument("--material", metavar="NAME",
                      help="also make a Principled BSDF material NAME fitted to the BRDF (keep it with --save)")
    brdf.add_argument("--save", metavar="OUT.blend", help="save the scene (with the fitted material) as OUT.blend")
    brdf.add_argument("--overwrite", action="store_true",
                      help="replace FILE if it exists, even if VisiBake did not write it (never its report's name, "
                           "FILE.visibake.json, unless VisiBake wrote that)")
    brdf.add_argument("--report", metavar="REPORT.json", help="write the run's report as JSON")
    brdf.add_argument("--no-progress", action="store_true", help="no progress bar")
    btf = commands.add_parser(
        "btf", help="simulate the BTF of a periodic micro-geometry tile: an image per light and view direction")
    btf.add_argument("input", help="the .blend holding the tile")
    btf.add_argument("--tile", metavar="NAME", required=True, help="the tile: a mesh object or a collection")
    btf.add_argument("--out", metavar="DIR", required=True,
                     help="write DIR/tvTTT_pvPPP/tlTTT_plPPP_tvTTT_pvPPP.<format> and DIR/btf.json")
    _setting_option(btf, "--format", APPEARANCE_SETTINGS["appearance_image_format"], default=True,
                    note="exr: linear RGB float; png: 8-bit sRGB")
    _setting_option(btf, "--image-size", APPEARANCE_SETTINGS["appearance_image_size"], "N", default=True)
    btf.add_argument("--rays-per-pixel", type=int, default=4, metavar="N", help="jittered rays per pixel")
    for option in ("--directions", "--bounces", "--resolution"):
        _setting_option(btf, option, APPEARANCE_SETTINGS["appearance_" + option.removeprefix("--")], "N",
                        default=True)
    btf.add_argument("--period", metavar="X,Y", help="the repeat in X and Y (default: the tile's bounding box)")
    btf.add_argument("--phong", metavar="KS,EXP", help="the paper's Lambert plus Phong micro-BRDF on every face")
    _setting_option(btf, "--seed", SETTINGS["seed"])
    _setting_option(btf, "--threads", PREFERENCE_SETTINGS["threads"], "N", note="default: the preference")
    _cluster_options(btf)
    btf.add_argument("--overwrite", action="store_true",
                     help="write into DIR even if it holds files VisiBake did not write: they are kept, and one "
                          "with the name of a file the BTF writes is refused, never replaced")
    btf.add_argument("--report", metavar="REPORT.json", help="write the run's report as JSON")
    btf.add_argument("--no-progress", action="store_true", help="no progress bar")
    lightfield = commands.add_parser(
        "lightfield", help="render a baked .blend's light field: a grid of views from parallel off-axis cameras, "
                           "in the HCI benchmark's layout")
    lightfield.add_argument("input", help="the baked .blend (or one to bake first: --bake-first)")
    lightfield.add_argument("--out", metavar="DIR", required=True,
                            help="write DIR/input_CamNNN.exr and .png, DIR/parameters.cfg and the centre view's "
                                 "gt_depth_lowres.pfm and gt_disp_lowres.pfm")
    lightfield.add_argument("--camera", metavar="NAME", help="the centre camera (default: the scene's camera)")
    lightfield.add_argument("--views", metavar="CxR",
                            help="columns x rows of views, e.g. 9x9 (default: the scene's Light Field settings, 9x9)")
    _setting_option(lightfield, "--baseline-mm", LIGHTFIELD_SETTINGS["lightfield_baseline_mm"], "MM", default=True)
    _setting_option(lightfield, "--focus-distance-m", LIGHTFIELD_SETTINGS["lightfield_focus_m"], "M", default=True)
    lightfield.add_argument("--image-size", metavar="WxH", help="pixels of each view, e.g. 512x512 (default 512x512)")
    _setting_option(lightfield, "--format", LIGHTFIELD_SETTINGS["lightfield_format"], default=True)
    _setting_option(lightfield, "--supersampling", LIGHTFIELD_SETTINGS["lightfield_supersampling"], "S", default=True)
    lightfield.add_argument("--bake-first", action="store_true",
                            help="bake the objects the views see first (the bake's options below apply); objects "
                                 "no view sees still cast shadows but are not baked")
    lightfield.add_argument("--objects", metavar="A,B",
                            help="with --bake-first: the objects to bake (default: every visible mesh a view sees)")
    lightfield.add_argument("--resolution-from-views", action="store_true",
                            help="with --bake-first: size each object's atlas to a texel per pixel where the views "
                                 "see it nearest, never above --resolution (or the texel density); objects with a "
                                 "resolution of their own keep it")
    lightfield.add_argument("--overwrite", action="store_true",
                            help="write into DIR even if it holds files VisiBake did not write: they are kept, and "
                                 "one with the name of a file the light field writes is refused, never replaced")
    lightfield.add_argument("--save", metavar="OUT.blend", help="save the scene (with what --bake-first baked)")
    lightfield.add_argument("--report", metavar="REPORT.json", help="write the run's report as JSON")
    _bake_setting_options(lightfield)
    _cluster_options(lightfield)
    for sub in (bake, relight):
        sub.add_argument("--preview-nodes", action="store_true",
                         help="wire the results into the objects' materials for preview (see preview; use with --save)")
    return parser


def _apply_settings(args, props) -> None:
    """Check, then copy command-line settings onto scene.visibake (the one settings model).

    Each value is checked first, by core's rule for it (core.settings.Setting.check):
    Blender clamps out-of-range values silently on assignment.
    """
    passes = None
    if args.passes is not None:
        passes = tuple(p.strip() for p in args.passes.split(",") if p.strip())
    if args.resolution is not None and args.texel_density is not None:
        raise BakeRefused("give one of --resolution (one atlas size) or --texel-density (sized by area), not both")
    given = {"directions": args.directions, "bounces": args.bounces, "resolution": args.resolution,
             "margin": args.margin, "threads": args.threads, "seed": args.seed,
             "texel_density": args.texel_density, "passes": passes, "footprint_samples": args.footprint_samples,
             "interleave": args.interleave, "target_error": args.target_error}
    for name, value in given.items():
        reason = None if value is None else SETTINGS[name].check(
            value, SCENE_SETTING_OPTIONS.get(name) or PREFERENCE_OPTIONS[name])
        if reason is not None:
            raise BakeRefused(reason)
    if args.preset is not None:
        props.preset = args.preset.upper()
    for name in ("directions", "bounces", "resolution", "mode", "shadows", "seed", "margin", "rotate",
                 "light_groups", "vertex_lookup", "footprint_samples", "interleave", "target_error"):
        value = getattr(args, name)
        if value is not None:
            setattr(props, name, value)
    if args.refine is not None:
        props.refine_vertex_objects = args.refine
    if args.cache_dir is not None:
        props.cache_dir = os.path.abspath(args.cache_dir)
    if args.no_sharp_contacts:
        props.sharp_contacts = False
    if args.no_stitch_seams:
        props.stitch_seams = False
    if args.no_cache:
        props.use_cache = False
    if args.texel_density is not None:
        props.texel_density = args.texel_density
    if passes is not None:
        props.passes = set(passes)


def _select_objects(args, scene) -> list:
    from .adapter import extract

    meshes = extract.scene_meshes(scene)
    if not args.objects:
        return meshes
    names = [n.strip() for n in args.objects.split(",") if n.strip()]
    by_name = {o.name: o for o in meshes}
    missing = [n for n in names if n not in by_name]
    if missing:
        # A curve, text, metaball or instancer takes part in the light but has no output: say so.
        reasons = [extract.why_not_a_target(scene.objects[n]) for n in missing if n in scene.objects]
        reasons = [r for r in reasons if r]
        raise BakeRefused(f"--objects: no visible mesh object named {', '.join(missing)} in the scene"
                          + (f" ({'; '.join(reasons)})" if reasons else ""))
    return [by_name[n] for n in names]


class _Progress:
    """A tqdm bar per stage on a terminal; one line per stage in logs and pipes."""

    def __init__(self, enabled: bool):
        self.enabled = enabled
        self.stage = None
        self.bar = None
        self.tqdm = None
        if enabled and sys.stderr.isatty():
            from tqdm import tqdm

            self.tqdm = tqdm

    def __call__(self, stage: str, fraction: float) -> None:
        if not self.enabled:
            return
        if stage != self.stage:
            self.close()
            self.stage = stage
            if self.tqdm is not None:
                self.bar = self.tqdm(total=100, desc=f"{stage:>10}", unit="%", file=sys.stderr,
                                     bar_format="{desc}: {percentage:3.0f}%|{bar}| {elapsed}<{remaining}")
            else:
                print(f"visibake: {stage} ...", file=sys.stderr, flush=True)
        if self.bar is not None:
            self.bar.update(int(100 * fraction) - self.bar.n)

    def note(self, text: str) -> None:
        """What the running stage is doing (core Stages.note): beside the bar, or a line of its own."""
        if not self.enabled:
            return
        if self.bar is not None:
            self.bar.set_postfix_str(text)
        elif text:
            print(f"visibake: {self.stage}: {text}", file=sys.stderr, flush=True)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None


def _load_input(args) -> None:
    if getattr(args, "input", None):
        path = os.path.abspath(args.input)
        if not os.path.isfile(path):
            raise BakeRefused(f"input file not found: {args.input}")
        if not path.lower().endswith(".blend"):
            raise BakeRefused(f"input must be a .blend file: {args.input}")
        try:
            bpy.ops.wm.open_mainfile(filepath=path)
        except RuntimeError as error:
            # Blender's reason is its last line ("File format is not supported", "Cannot read file ...").
            reason = str(error).strip().splitlines()[-1] if str(error).strip() else "cannot be read"
            raise BakeRefused(f"not a readable .blend file: {args.input} ({reason.removeprefix('Error: ')})") from None
    else:
        from .adapter import demo_scene

        # read_homefile keeps the preferences, so VisiBake stays enabled (factory
        # settings would disable it in the middle of its own command).
        bpy.ops.wm.read_homefile(use_empty=True)
        demo_scene.build_demo_scene(bpy.context.scene)


def _setups(args):
    """A callable making the lighting setups from the scene's lights and world, or None."""
    setups_file, sweep = getattr(args, "setups", None), getattr(args, "sun_sweep", None)
    if setups_file and sweep:
        raise BakeRefused("give either --setups or --sun-sweep, not both")
    if not setups_file and not sweep:
        return None
    if not args.out:
        raise BakeRefused("--setups and --sun-sweep write one folder per setup: give --out DIR")
    if sweep:
        start, end, steps = lighting_setups.parse_sweep(sweep)
        return lambda lights, world: lighting_setups.sun_sweep(start, end, steps, args.latitude, args.day,
                                                               lights, world, args.sun)
    path = os.path.abspath(setups_file)
    if not os.path.isfile(path):
        raise BakeRefused(f"--setups: file not found: {setups_file}")
    return lambda lights, world: lighting_setups.load_setups(path, lights, world)


def _check_destinations(args, out_dir: str | None) -> None:
    """Refuse (exit 2) before any work if a file or folder the command writes cannot be written."""
    report_path = getattr(args, "report", None)
    if args.command == "demo":
        report_path = report_path or os.path.join(out_dir, "report.json")
    check_destinations([(out_dir, FOLDER, "--out"), (getattr(args, "save", None), FILE, "--save"),
                        (report_path, FILE, "--report")])
    if args.command == "demo":
        # Not named by the user: the one rule of core.outputs.ownership (an earlier demo's report lists both).
        refuse_foreign([os.path.join(out_dir, "preview_render.png")] + ([] if args.report else [report_path]))


def run_preview(args) -> int:
    """``preview``: what Show Baked Lighting (or Remove Preview) does, on a saved file."""
    from .adapter import preview_nodes

    _check_destinations(args, None)
    _load_input(args)
    if args.remove:
        changed = preview_nodes.remove_preview()
        print(f"visibake: preview removed from {changed} material(s)", flush=True)
    else:
        wired, warnings = preview_nodes.add_preview(_select_objects(args, bpy.context.scene))
        for warning in warnings:
            print(f"visibake: warning: {warning}", file=sys.stderr, flush=True)
        print(f"visibake: baked lighting shown in {wired} material(s)", flush=True)
    _save_blend(args.save, [])
    return EXIT_OK


def run_clear_cache(args) -> int:
    """``clear-cache``: what Clear Cache does."""
    from .adapter import cache_status

    _load_input(args)
    if args.cache_dir is not None:
        bpy.context.scene.visibake.cache_dir = os.path.abspath(args.cache_dir)
    slots, freed = cache_status.clear(bpy.context.scene)
    print(f"visibake: cleared {slots} cached table(s), {freed / 2**20:.1f} MiB", flush=True)
    return EXIT_OK


def run_volume(args) -> int:
    """``volume``: light each Volume object from its scattering tables and write its grids. The
    scene's Volumes settings travel in the .blend; the options override them."""
    from .adapter import volume_job

    out_dir = os.path.abspath(args.out)
    _check_destinations(args, out_dir)
    cluster = _cluster(args)
    _load_input(args)
    scene = bpy.context.scene
    if args.cache_dir is not None:
        scene.visibake.cache_dir = os.path.abspath(args.cache_dir)
    if args.no_cache:
        scene.visibake.use_cache = False
    values = {}
    for name in VOLUME_SETTINGS:
        spec, given = VOLUME_SETTINGS[name], getattr(args, name.removeprefix("volume_"))
        value = getattr(scene.visibake, name) if given is None else given
        if not spec.minimum <= value <= spec.maximum:
            raise BakeRefused(f"--{name.removeprefix('volume_')} {value}: use a value from {spec.minimum} to "
                              f"{spec.maximum}")
        values[name] = value
    volumes = volume_job.scene_volumes(scene)
    if args.objects:
        names = [n.strip() for n in args.objects.split(",") if n.strip()]
        by_name = {o.name: o for o in volumes}
        missing = [n for n in names if n not in by_name]
        if missing:
            raise BakeRefused(f"--objects: no visible volume (Volume object or mesh with a Principled Volume) named "
                              f"{', '.join(missing)} in the scene")
        volumes = [by_name[n] for n in names]
    threads = args.threads if args.threads is not None else volume_job.preferred_threads()
    progress = _Progress(not args.no_progress)
    try:
        outcome = volume_job.VolumeJob(scene, volumes, out_dir, values["volume_resolution"],
                                       values["volume_directions"], values["volume_bounces"], values["volume_points"],
                                       scene.visibake.seed if args.seed is None else args.seed, threads,
                                       progress, device_name=args.device, cluster=cluster).run()
    finally:
        progress.close()
    made_folders: list = []
    try:
        if args.save:
            _save_blend(args.save, made_folders)
            outcome.report["files"].append(os.path.abspath(args.save))
        if args.report:
            job.write_report(args.report, outcome.report)
    except BaseException:
        outcome.rollback()
        raise
    for warning in outcome.report["warnings"]:
        print(f"visibake: warning: {warning}", file=sys.stderr, flush=True)
    for entry in outcome.report["volumes"]:
        done = f"-> {entry['output']!r}" if entry["output"] else "skipped"
        print(f"visibake: volume {entry['name']!r} {'x'.join(map(str, entry['grid']))}, "
              f"{entry['active_voxels']:,} voxels with medium {done}", flush=True)
    print(f"visibake: {len(outcome.report['files'])} file(s) written in {outcome.report['seconds']:.1f} s", flush=True)
    return EXIT_OK


def _pair(text: str, option: str) -> tuple[float, float]:
    try:
        first, second = (float(part) for part in text.split(","))
    except ValueError:
        raise BakeRefused(f"{option} {text!r}: give two numbers separated by a comma") from None
    if not (math.isfinite(first) and math.isfinite(second)):
        raise BakeRefused(f"{option} {text!r}: give finite numbers")
    return first, second


def _tile_and_settings(args):
    """The tile and the simulation settings of a ``brdf`` or ``btf`` command."""
    from ..core.appearance import gonio
    from .adapter import tile_io

    period = _pair(args.period, "--period") if args.period else None
    phong = _pair(args.phong, "--phong") if args.phong else None
    if phong is not None and not (0 <= phong[0] <= 1 and phong[1] >= 0):
        raise BakeRefused(f"--phong {args.phong!r}: the weight lies in [0, 1] and the exponent is >= 0")
    _load_input(args)
    scene = bpy.context.scene
    # The scene's Materials from Micro-Geometry settings travel in the .blend; the options override them.
    for name in ("lights", "views", "directions", "bounces", "resolution", "image_size"):
        spec = APPEARANCE_SETTINGS["appearance_" + name]
        given = getattr(args, name, None)
        value = getattr(scene.visibake, spec.name) if given is None else given
        if hasattr(args, name) and not spec.minimum <= value <= spec.maximum:
            raise BakeRefused(f"--{name.replace('_', '-')} {value}: use a value from {spec.minimum} to "
                              f"{spec.maximum}")
        setattr(args, name, value)
    if args.command == "btf" and args.format is None:
        args.format = scene.visibake.appearance_image_format
    tile = tile_io.read_tile(scene, args.tile, period, phong)
    seed = scene.visibake.seed if args.seed is None else args.seed
    settings = gonio.GonioSettings(directions=args.directions, bounces=args.bounces, resolution=args.resolution,
                                   view_rays=getattr(args, "view_rays", 128), seed=seed,
                                   threads=args.threads if args.threads is not None else tile_io.preferred_threads())
    return tile, settings


def _run_appearance(args, work) -> dict:
    """``work(progress)`` under a progress bar; then its report written (--report) and its
    warnings printed. Returns the report."""
    progress = _Progress(not args.no_progress)
    try:
        report = work(progress)
    finally:
        progress.close()
    if args.report:
        job.write_report(args.report, report)
    for warning in report["warnings"]:
        print(f"visibake: warning: {warning}", file=sys.stderr, flush=True)
    return report


def run_brdf(args) -> int:
    """``brdf``: simulate a tile's BRDF (core.appearance.gonio) and write its table."""
    from .adapter import tile_io

    output_format = args.format or ("table" if args.out.lower().endswith(".npz") else "merl")
    if output_format == "merl" and not args.out.lower().endswith((".binary", ".merl")):
        raise BakeRefused(f"--out {args.out!r}: a MERL file ends in .binary (or .merl, as pbrt expects)")
    if output_format in ("table", "bsdf") and not args.out.lower().endswith(".npz"):
        raise BakeRefused(f"--out {args.out!r}: a tabulated BSDF ends in .npz")
    _check_destinations(args, None)
    cluster = _cluster(args)
    tile, settings = _tile_and_settings(args)
    report = _run_appearance(args, lambda progress: tile_io.run_brdf(
        tile, args.out, output_format, args.lights, args.views, settings, args.overwrite, progress, cluster))
    fit = report.get("principled_fit")
    if fit is not None:
        print(f"visibake: Principled BSDF fit ({fit['model']}): base colour "
              f"({', '.join(f'{x:.3f}' for x in fit['base_color'])}), roughness {fit['roughness']:.3f}, specular "
              f"IOR level {fit['specular_ior_level']:.3f}, anisotropic {fit['anisotropic']:.3f}, sheen "
              f"{fit['sheen_weight']:.3f}; relative RMSE of the fit {100 * fit['relative_rmse']:.1f}%", flush=True)
        if args.material:
            made = tile_io.make_material(args.material, fit)
            print(f"visibake: material {made.name!r} made from the fit", flush=True)
    if args.save:
        _save_blend(args.save, [])
    print(f"visibake: {args.lights} x {args.views} BRDF samples of {args.tile!r} ({report['samples']:,} surface "
          f"samples, {settings.directions} directions, {settings.bounces} bounces) -> {report['output']!r} in "
          f"{report['seconds']:.1f} s; largest directional albedo {report['max_directional_albedo']:.3f}", flush=True)
    return EXIT_OK


def run_btf(args) -> int:
    """``btf``: simulate a tile's BTF on the UBO2003 directions, in the UTIA folder layout."""
    from .adapter import tile_io

    if not 1 <= args.rays_per_pixel <= 256:
        raise BakeRefused(f"--rays-per-pixel {args.rays_per_pixel}: use 1 to 256")
    cluster = _cluster(args)
    tile, settings = _tile_and_settings(args)
    report = _run_appearance(args, lambda progress: tile_io.run_btf(
        tile, args.out, args.format, args.image_size, settings, args.rays_per_pixel, args.overwrite, progress,
        cluster))
    print(f"visibake: BTF of {args.tile!r}: {report['images']} images of {args.image_size}x{args.image_size} -> "
          f"{report['output']!r} in {report['seconds']:.1f} s", flush=True)
    return EXIT_OK


def _pair_of_counts(text: str, option: str) -> tuple[int, int]:
    """'9x9' as (9, 9); refuses anything else."""
    parts = text.lower().replace("*", "x").split("x")
    if len(parts) != 2 or not all(part.strip().isdigit() for part in parts):
        raise BakeRefused(f"{option} {text!r}: give two whole numbers as AxB, e.g. 9x9")
    return int(parts[0]), int(parts[1])


def run_lightfield(args) -> int:
    """``lightfield``: render a baked scene's light field (adapter.lightfield_io), baking the
    objects the views see first with --bake-first."""
    from .adapter import lightfield_io

    _check_destinations(args, None)
    _load_input(args)
    scene = bpy.context.scene
    props = scene.visibake
    columns, rows = (_pair_of_counts(args.views, "--views") if args.views
                     else (props.lightfield_columns, props.lightfield_rows))
    width, height = (_pair_of_counts(args.image_size, "--image-size") if args.image_size
                     else (props.lightfield_width, props.lightfield_height))
    values = {"lightfield_columns": (columns, "--views"), "lightfield_rows": (rows, "--views"),
              "lightfield_width": (width, "--image-size"), "lightfield_height": (height, "--image-size"),
              "lightfield_baseline_mm": (props.lightfield_baseline_mm if args.baseline_mm is None else args.baseline_mm,
                                         "--baseline-mm"),
              "lightfield_focus_m": (props.lightfield_focus_m if args.focus_distance_m is None
                                     else args.focus_distance_m, "--focus-distance-m"),
              "lightfield_supersampling": (props.lightfield_supersampling if args.supersampling is None
                                           else args.supersampling, "--supersampling")}
    for name, (value, option) in values.items():
        reason = LIGHTFIELD_SETTINGS[name].check(value, option)
        if reason is not None:
            raise BakeRefused(reason)
    output_format = args.format or props.lightfield_format
    if args.resolution_from_views and not args.bake_first:
        raise BakeRefused("--resolution-from-views sizes the bake: it needs --bake-first")
    cluster = _cluster(args)
    progress = _Progress(not args.no_progress)
    extra: dict = {}
    try:
        if args.bake_first:
            _apply_settings(args, props)
            camera, _, views, clip = lightfield_io.plan_views(scene, args.camera, (columns, rows),
                                                              values["lightfield_baseline_mm"][0],
                                                              values["lightfield_focus_m"][0], (width, height), [])
            seen, unseen = lightfield_io.objects_in_views(_select_objects(args, scene), views, *clip)
            if not seen:
                raise BakeRefused("--bake-first: no object to bake is in any view (check --camera and --objects)")
            sizing: list[str] = []
            densities = (lightfield_io.view_densities(seen, camera, views, (columns, rows), clip, sizing)
                         if args.resolution_from_views else None)
            baked = job.run_bake(bpy.context, seen, None, False, progress, device_name=args.device,
                                 threads=args.threads, view_densities=densities, cluster=cluster)
            extra["bake"] = {"objects": [o.name for o in seen], "skipped_unseen": [o.name for o in unseen],
                             "seconds": baked.report.get("total_seconds"),
                             "warnings": sizing + baked.report.get("warnings", []),
                             "resolution_from_views": bool(args.resolution_from_views),
                             "resolutions": {entry["name"]: entry["resolution"] for entry in baked.report["objects"]
                                             if entry["output"] and entry.get("mode", "atlas") == "atlas"}}
        outcome = lightfield_io.LightFieldJob(
            scene, args.camera, args.out, (columns, rows), values["lightfield_baseline_mm"][0],
            values["lightfield_focus_m"][0], (width, height), output_format, args.device or "auto", args.overwrite,
            progress, extra, values["lightfield_supersampling"][0], cluster).run()
    finally:
        progress.close()
    report = outcome.report
    made_folders: list = []
    if args.save:
        _save_blend(args.save, made_folders)
    if args.report:
        job.write_report(args.report, report)
    for warning in report["warnings"]:
        print(f"visibake: warning: {warning}", file=sys.stderr, flush=True)
    if extra.get("bake", {}).get("resolution_from_views"):
        sizes = ", ".join(f"{name} {size[0]}" for name, size in extra["bake"]["resolutions"].items())
        print(f"visibake: --resolution-from-views: atlases of {sizes}", flush=True)
    for warning in extra.get("bake", {}).get("warnings", []):
        print(f"visibake: warning (bake): {warning}", file=sys.stderr, flush=True)
    if extra.get("bake", {}).get("skipped_unseen"):
        print(f"visibake: --bake-first skipped {len(extra['bake']['skipped_unseen'])} object(s) no view sees: "
              f"{', '.join(extra['bake']['skipped_unseen'][:8])}", flush=True)
    print(f"visibake: light field of {report['views']} views ({columns}x{rows}) at {width}x{height} -> "
          f"{report['output']!r}: rendered in {report['render_s']:.2f} s ({report['renderer']}), files written in "
          f"{report['write_s']:.2f} s; disparity {report['disparity_range'][0]:.1f} to "
          f"{report['disparity_range'][1]:.1f} px", flush=True)
    return EXIT_OK


def run_farm_part(args) -> int:
    """``farm-part``: answer one range of the job folder's pending step (core.distributed.farm)."""
    from ..core.distributed import farm

    if not os.path.isdir(args.job):
        raise BakeRefused(f"--job {args.job!r}: no such folder (the step before this part makes it)")
    if args.part < 0:
        raise BakeRefused(f"--part {args.part}: parts are numbered from 0")
    done = farm.run_part(args.job, args.part, args.threads or 0)
    print(f"visibake: farm part: {done}", flush=True)
    return EXIT_OK


def run_farm_check(args) -> int:
    """``farm-check``: the last task of a farm job; the job fails unless the bake finished."""
    from ..core.distributed import farm

    state = farm.read_pending(args.job)
    if not state.get("done"):
        raise BakeRefused(f"the bake in {args.job} did not finish within the job's steps (it waits for the parts "
                          f"of call {state.get('call')}): submit it again with more Steps")
    print(f"visibake: farm bake in {args.job} finished", flush=True)
    return EXIT_OK


def run(args) -> int:
    if args.command == "farm-part":
        return run_farm_part(args)
    if args.command == "farm-check":
        return run_farm_check(args)
    if args.command == "lightfield":
        return run_lightfield(args)
    if args.command == "brdf":
        return run_brdf(args)
    if args.command == "btf":
        return run_btf(args)
    if args.command == "volume":
        return run_volume(args)
    if args.command == "preview":
        return run_preview(args)
    if args.command == "clear-cache":
        return run_clear_cache(args)
    if getattr(args, "preview_nodes", False) and not args.save:
        raise BakeRefused("--preview-nodes changes the materials: give --save OUT.blend to keep them")
    out_dir = os.path.abspath(args.out) if args.out else None
    if args.command == "demo" and out_dir is None:
        out_dir = os.path.abspath("visibake_demo")
    _check_destinations(args, out_dir)
    cluster = _cluster(args) if args.command in ("bake", "demo") else None
    if args.command == "farm-step":
        from ..core.distributed import farm

        cluster = farm.FarmOptions(os.path.abspath(args.job), args.parts)
        cluster.validate()
        if not (args.out or args.save):
            raise BakeRefused("farm-step: give --out DIR or --save OUT.blend, or the last step's results are lost")
        if farm.read_pending(cluster.folder).get("done"):
            print(f"visibake: farm step: the bake in {cluster.folder} is finished; nothing to do", flush=True)
            return EXIT_OK
    _load_input(args)
    scene = bpy.context.scene
    props = scene.visibake
    _apply_settings(args, props)
    objects = _select_objects(args, scene)
    previews = bool(args.previews) or args.command == "demo"
    if args.command == "demo" and args.cache_dir is None:
        # The demo scene is never saved: keep its cache with its outputs, not in the
        # user's profile, so a second run shows a cache hit and one folder holds all.
        props.cache_dir = os.path.join(out_dir, "visibake_cache")
    progress = _Progress(not args.no_progress)
    setups = _setups(args)
    implicit = [os.path.join(out_dir, name) for name in ("report.json", "preview_render.png")] \
        if args.command == "demo" else []
    existed = {os.path.abspath(p) for p in (args.save, args.report, *implicit) if p and os.path.exists(p)}
    try:
        outcome = job.run_bake(bpy.context, objects, out_dir, previews, progress,
                               relight_only=args.command == "relight", setups=setups, device_name=args.device,
                               threads=args.threads, cluster=cluster, hold_replaced=True,
                               fixed_directions=getattr(args, "directions", None) is not None)
    except Exception as error:
        from ..core.distributed.farm import PartsPending

        if not isinstance(error, PartsPending):
            raise
        # Not a failure: this step went as far as the parts allow, and the scene is as it was.
        print(f"visibake: farm step: waiting for the parts of call {error.call} ({error.folder})", flush=True)
        return EXIT_OK
    finally:
        progress.close()
    written, made_folders = [], []
    try:
        _after_bake(args, scene, outcome, out_dir, written, made_folders)
    except BaseException as error:
        # As a cancel: what the bake created goes again (the scene's UV maps, images and colour
        # attributes, what it wrote into the output folder, and the files named by options that
        # did not exist before), so no half of it stays behind.
        outcome.rollback()
        remove_written(set(written) - existed, reversed(made_folders))
        if isinstance(error, OSError):
            raise BakeRefused(f"could not write {error.filename or 'the results'}: {error.strerror or error}; "
                              "nothing was kept") from error
        raise
    outcome.keep()
    if args.command == "farm-step":
        from ..core.distributed.farm import mark_done

        mark_done(cluster.folder)
    print(format_summary(outcome.report), flush=True)
    return EXIT_OK


def _save_blend(path: str, made_folders: list) -> None:
    """Save a copy of the open file as ``path``, making its folder (Blender does not); the
    folders made are added to ``made_folders``, deepest first. A save Blender cannot do (a full
    disk) is refused as the user's to fix."""
    path = os.path.abspath(path)
    folder = os.path.dirname(path)
    missing = []
    while not os.path.exists(folder):
        missing.append(folder)
        folder = os.path.dirname(folder)
    os.makedirs(os.path.dirname(path), exist_ok=True)
    made_folders += missing
    try:
        bpy.ops.wm.save_as_mainfile(filepath=path, copy=True)
    except RuntimeError as error:
        reason = str(error).strip().splitlines()[-1] if str(error).strip() else "Blender could not save it"
        raise BakeRefused(f"--save {path}: {reason.removeprefix('Error: ')}") from None


def _after_bake(args, scene, outcome, out_dir: str | None, written: list, made_folders: list) -> None:
    """The command's steps after the bake: preview nodes, --save, the demo's render, the report.

    ``written`` and ``made_folders`` are extended with the files and folders made, as they are made.
    """
    report = outcome.report
    if getattr(args, "preview_nodes", False):
        from .adapter import preview_nodes

        _, warnings = preview_nodes.add_preview(
            [bpy.data.objects[entry["name"]] for entry in report["objects"] if entry["output"]])
        report["warnings"] += warnings
    if args.save:
        _save_blend(args.save, made_folders)
        written.append(os.path.abspath(args.save))
        report["files"].append(os.path.abspath(args.save))
    if args.command == "demo":
        from .adapter import preview_render as preview

        started = time.perf_counter()
        render_path = os.path.join(out_dir, "preview_render.png")
        # None for vertex-mode objects: the preview shows their colour attribute.
        uv_maps = {entry["name"]: entry["uv_map"] if entry.get("mode", "atlas") == "atlas" else None
                   for entry in report["objects"] if entry["output"]}
        if preview.render_baked_preview(scene, list(uv_maps), render_path, uv_maps):
            written.append(render_path)
            report["files"].append(render_path)
        report["stage_seconds"]["preview_render"] = round(time.perf_counter() - started, 4)
    report_path = args.report or (os.path.join(out_dir, "report.json") if args.command == "demo" else None)
    if report_path:
        job.write_report(report_path, report)


def format_summary(report: dict) -> str:
    """The summary printed after a bake (core.outputs.summary.summary_lines)."""
    return "\n".join(report_texts.summary_lines(report))


def main(argv) -> int:
    """Entry point of the command; returns the exit status."""
    parser = build_parser()
    try:
        args = parser.parse_args(list(argv))
    except SystemExit as exit_request:
        return int(exit_request.code or 0)
    try:
        return run(args)
    except BakeRefused as error:
        print(f"visibake: error: {error}", file=sys.stderr, flush=True)
        return EXIT_BAD_INPUT
    except (Cancelled, KeyboardInterrupt):
        print("visibake: cancelled; nothing was written", file=sys.stderr, flush=True)
        return EXIT_FAILURE
    except Exception:
        # Not the user's input (that is a BakeRefused): a bug in VisiBake, said as such.
        traceback.print_exc()
        print("visibake: failed: this is a bug in VisiBake, not a problem with your input; please report it "
              "with the traceback above", file=sys.stderr, flush=True)
        return EXIT_FAILURE
