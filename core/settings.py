"""Every setting of a bake and of its layout: choices, defaults, limits, help, validation.

The one description of each setting is its :class:`Setting` in :data:`SETTINGS` (the
scene's settings, and the few only the core sets), :data:`OBJECT_SETTINGS` (an
object's own) or :data:`PREFERENCE_SETTINGS` (the machine's). The Blender properties
(panels/properties.py, panels/preferences.py) and the command line
(operators/cli.py) take their names, defaults, ranges, choices and help text from
these tables, and the dataclasses below take their defaults from them.

:class:`BakeSettings` holds what changes the result of a bake (it goes into the
report and, in part, into the visibility cache's key), :class:`LayoutSettings` what
decides where the samples lie. ``validate()`` on each is the one check of a complete
set of values; :meth:`Setting.check` is the same rule for one value, for a front end
that must refuse a value before storing it.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, fields

from .errors import BakeRefused

# The largest C int: Blender stores int settings in one, and refuses or wraps beyond it.
INT_LIMIT = 2**31 - 1
# Cycles' hard limit on bounces (max_bounces and diffuse_bounces: hard_max 1024 in bpy 4.2 to 5.3).
MAX_BOUNCES = 1024
# Worker threads beyond the cores only contend for them; 0 means all.
CPU_COUNT = os.cpu_count() or 1

LIGHTING_PASSES = ("lighting", "direct", "indirect", "irradiance")


PASSES = ("lighting", "direct", "indirect", "irradiance", "ao")


SHADOW_MODES = ("fractions", "exact")


SAMPLE_MODES = ("atlas", "vertex")


VERTEX_LOOKUPS = ("interpolate", "nearest")


# 'auto' chooses one of SAMPLE_MODES per object (core.sampling.layout).
LAYOUT_MODES = ("auto",) + SAMPLE_MODES


DEVICES = ("auto", "gpu", "cpu")


@dataclass(frozen=True)
class Setting:
    """One setting: its type, default, limits, choices and the one help text.

    name : the identifier (a dataclass field, a Blender property, a command-line option's dest)
    type : int, float, bool, str, or tuple (a non-empty subset of ``choices``)
    title : what the UI calls it
    label : what a refusal calls it; the name with spaces when empty
    minimum, maximum : hard limits (refused outside them); None: none
    soft_min, soft_max : the range a slider offers; None: the hard limits
    choices : (value, title, help) of each allowed value; empty: any value of ``type``
    refusal : how a value below ``minimum`` is refused (``{label}``, ``{minimum}``, ``{value}``)
    on_scene : a property of the scene's settings (scene.visibake) has this name; False for
        the settings only the core (and its callers) set
    """

    name: str
    type: type
    default: object
    title: str
    help: str
    label: str = ""
    minimum: float | None = None
    maximum: float | None = None
    soft_min: float | None = None
    soft_max: float | None = None
    choices: tuple[tuple[str, str, str], ...] = ()
    refusal: str = "{label} must be >= {minimum}, got {value}"
    on_scene: bool = True
    over_maximum: str = ""  # why the maximum is what it is, after "must be <= {maximum}"

    @property
    def values(self) -> tuple[str, ...]:
        """The allowed values of a setting with choices."""
        return tuple(value for value, _, _ in self.choices)

    def check(self, value, label: str | None = None) -> str | None:
        """Why ``value`` cannot be used, in one line naming it ``label``; None if it can."""
        label = label or self.label or self.name.replace("_", " ")
        if self.type is tuple:
            unknown = [v for v in value if v not in self.values]
            if unknown or not value:
                return (f"{label}: choose at least one of {', '.join(self.values)}"
                        + (f" (unknown: {', '.join(unknown)})" if unknown else ""))
            return None
        if self.choices and value not in self.values:
            return f"{label} must be one of {', '.join(self.values)}, got {value!r}"
        # Written as 'not >=' so that NaN is refused too.
        if self.minimum is not None and not value >= self.minimum:
            return self.refusal.format(label=label, minimum=self.minimum, value=value)
        if self.maximum is not None and not value <= self.maximum:
            return f"{label} must be <= {self.maximum}{self.over_maximum}, got {value}"
        # Blender's int properties are C ints, and no count or size of a bake is near the limit.
        if self.type is int and not -INT_LIMIT <= value <= INT_LIMIT:
            return f"{label} must be <= {INT_LIMIT}, got {value}"
        if self.type is float and not math.isfinite(value):
            return f"{label} must be a finite number, got {value}"
        return None


def _table(*settings: Setting) -> dict[str, Setting]:
    return {setting.name: setting for setting in settings}


_WITHOUT_VALUE = "{label} must be >= {minimum}"


# What each preset sets; any later change to one of these makes the preset Custom.
PRESETS = {
    "DRAFT": {"directions": 64, "bounces": 1, "resolution": 128, "shadows": "exact", "rotate": False},
    "PRODUCTION": {"directions": 256, "bounces": 3, "resolution": 512, "shadows": "exact", "rotate": True},
}


def _preset_help(values: dict, purpose: str) -> str:
    bounces = values["bounces"]
    return (f"{values['directions']} directions, {bounces} bounce{'' if bounces == 1 else 's'}, "
            f"{values['resolution']} texels, {values['shadows']} shadows"
            + (", rotated direction set" if values.get("rotate") else "") + f": {purpose}")


_MODE_CHOICES = (("atlas", "Atlas", "Texture atlas (UV map), results as images"),
                 ("vertex", "Vertex", "Per-vertex tables, results as colour attributes VB_<pass>"))


SETTINGS = _table(
    # What changes the result: BakeSettings.
    Setting("directions", int, 128, "Directions", minimum=1, soft_min=16, soft_max=1024,
            help="Size of the global direction set: rays per texel for visibility (more: less noise, slower)"),
    Setting("target_error", float, 0.0, "Target Error", minimum=0.0, maximum=1.0, soft_max=0.2,
            help="If above zero, the relative RMS error per texel to aim at (0.03: 3 percent, against a converged "
                 "Cycles bake): VisiBake bakes a pilot at few directions, estimates its own error from it, and "
                 "chooses the direction count that meets the target (Directions is then ignored); the report "
                 "gives the estimate. 0: the Directions as set"),
    Setting("chosen_directions", int, 0, "Chosen Directions", minimum=0,
            help="The direction count the last bake at a Target Error chose (0: none yet): the next bake starts "
                 "its pilot there and keeps it where the estimate meets the target, and Relight reuses it"),
    Setting("bounces", int, 2, "Bounces", minimum=0, maximum=MAX_BOUNCES, soft_max=8,
            over_maximum=" (Cycles' limit)",
            help="Diffuse bounces of indirect light (as Cycles' Diffuse bounces)"),
    Setting("shadows", str, "exact", "Shadows", help="How direct light is shadowed",
            choices=(("fractions", "Fractions", "Shadows from the precomputed visibility (no ray at lighting time, "
                                                "soft)"),
                     ("exact", "Exact", "One shadow ray per texel and light (sharp, traced at every bake)"))),
    Setting("shadow_regions", int, 32, "Shadow Regions", minimum=1, on_scene=False,
            help="Number of regions of the shadow fractions"),
    Setting("rotate", bool, False, "Rotate Directions",
            help="Randomly rotate the direction set (seeded): structured artefacts become noise"),
    Setting("seed", int, 0, "Seed", minimum=0, help="Seed of the direction rotation"),
    Setting("interleave", int, 4, "Interleaved Rotations", minimum=1, maximum=8,
            help="Neighbouring texels use different rotations of the direction set (a tile of this many texels "
                 "squared, one rotation each) and their indirect light is averaged over the 3 x 3 texels around "
                 "each (at most the tile), so the fixed set's streaks from small bright patches become fine noise "
                 "the average removes (1: one set for every texel)"),
    Setting("passes", tuple, ("lighting",), "Passes", help="Which passes to write",
            choices=tuple((p, p.capitalize(), f"Write the {p} pass") for p in PASSES)),
    Setting("margin", int, 4, "Margin", minimum=0, soft_max=32,
            help="Texels the results are extended into the gutter so filtering never pulls in black"),
    Setting("area_light_samples", int, 8, "Area Light Samples", minimum=1, refusal=_WITHOUT_VALUE, on_scene=False,
            help="Per side: a lamp with an extent (area lamp, sun with an angle, point or spot with a "
                 "radius) is integrated with this many squared stratified points per texel"),
    Setting("footprint_samples", int, 16, "Texel Footprint Samples", minimum=1, maximum=256, soft_max=64,
            help="Points per texel spread over its footprint on the surface, as Cycles' bake spreads its samples "
                 "(over the texel's area on its own face): the table's rays start from them and exact "
                 "shadows are averaged over them, so shadow edges and contacts are anti-aliased (1: texel "
                 "centres only)"),
    # Not the scene's: the Blender adapter gives the running Cycles' width (operators.adapter.compat).
    Setting("footprint_width", float, 1.0, "Texel Footprint Width", minimum=0.0, maximum=4.0, on_scene=False,
            help="Width of the box, in texels, each texel's footprint points are spread over (Cycles' bake: "
                 "1 since Blender 5.2.1, 0.5 in Blender 4.2 to 5.2.0; 0 puts them all at the centre)"),
    Setting("sharp_contacts", bool, True, "Sharp Contacts",
            help="Where a ray of the table lands within two texels of its target (objects resting on others, "
                 "corners), light it at the landing point with exact shadow rays, and with the sky as open as it "
                 "is there, instead of reading the target's texels, so contact shadows are not blurred by the "
                 "texel size (exact shadows only)"),
    Setting("stitch_seams", bool, True, "Stitch Seams",
            help="Move the texels along UV seams between smooth faces, as little as possible, until both sides "
                 "of each seam read the same light under bilinear filtering, so no line shows along a seam "
                 "(Cycles does not stitch: off matches its texels)"),
    Setting("emitter_samples", int, 16, "Emitter Samples", minimum=1, refusal=_WITHOUT_VALUE, on_scene=False,
            help="Points per emissive object for direct sampling of small emitters, at least one on "
                 "each of its flat faces where it has no more faces than points"),
    # A preference (the machine's), not the scene's.
    Setting("threads", int, 0, "Threads", minimum=0, maximum=CPU_COUNT, on_scene=False,
            over_maximum=" (this machine's cores)",
            help="Worker threads for ray tracing and gathers (0: all cores)"),
    Setting("chunk_rays", int, 1 << 20, "Rays per Batch", minimum=1, on_scene=False,
            help="Rays traced per batch; bounds the memory of the tracing stage"),
    Setting("light_groups", bool, False, "Light Groups",
            help="Also write every lighting pass per light group (a lamp's Light Group, else each lamp; the world; "
                 "each emitting object), so lights can be re-mixed without another bake"),
    Setting("vertex_lookup", str, "interpolate", "Vertex Lookup",
            help="How light is read where a ray lands on a vertex-mode object",
            choices=(("interpolate", "Interpolate", "Mix the three vertices of the triangle a ray lands on"),
                     ("nearest", "Nearest", "The paper's variant: the nearest vertex of that triangle"))),
    # Where the samples lie: LayoutSettings.
    Setting("resolution", int, 256, "Resolution", minimum=1, soft_min=16, soft_max=4096,
            help="Atlas width and height in texels for objects without their own resolution"),
    Setting("texel_density", float, 0.0, "Texels per Unit", minimum=0.0, soft_max=1024.0,
            help="If above zero, size each atlas from the object's surface area instead of Resolution"),
    Setting("mode", str, "auto", "Mode", help="Where samples live",
            choices=(("auto", "Auto", "Texture atlas; vertex tables for meshes too dense or too big to unwrap, "
                                      "or where unwrapping fails"),) + _MODE_CHOICES),
    # How and where a bake runs, without changing its result.
    Setting("preset", str, "CUSTOM", "Preset", help="Set directions, bounces, resolution and shadows together",
            choices=(("DRAFT", "Draft", _preset_help(PRESETS["DRAFT"], "a quick look")),
                     ("PRODUCTION", "Production", _preset_help(PRESETS["PRODUCTION"], "final quality")),
                     ("CUSTOM", "Custom", "The settings below as they are"))),
    Setting("bake_all", bool, False, "All Objects",
            help="Bake every visible mesh object instead of the selected ones"),
    Setting("use_cache", bool, True, "Cache Visibility",
            help="Keep the visibility tables on disk, so bakes after changes to lights, materials or the world "
                 "(and Relight) skip the visibility stage"),
    Setting("cache_dir", str, "", "Cache Folder",
            help="Where the visibility cache lives; empty: a visibake_cache folder beside the saved .blend, "
                 "else VisiBake's folder in your user profile"),
    Setting("refine_vertex_objects", bool, False, "Refine Coarse Vertex Objects",
            help="Where a vertex-mode object's triangles are too large for its light (a shadow edge inside "
                 "them), bake a copy with those faces subdivided in its place and hide the original; your mesh "
                 "is never changed"),
    Setting("output_dir", str, "", "Output Folder",
            help="Folder for the EXR files (<folder>/<object>/<pass>.exr); empty: images in the .blend only"),
)


# An object's own settings; each overrides the scene's setting of the same name.
OBJECT_SETTINGS = _table(
    Setting("role", str, "INCLUDE", "Role",
            help="Whether this object gets results or only takes part in the light transport",
            choices=(("INCLUDE", "Bake", "Bake this object when it is selected, or with All Objects"),
                     ("OCCLUDE", "Occlude Only", "Never bake this object: it only casts shadows and reflects "
                                                 "light"))),
    Setting("resolution", int, 0, "Resolution", minimum=0, soft_max=4096,
            help="Atlas size of this object in texels (0: the scene's setting)"),
    Setting("texel_density", float, 0.0, "Texels per Unit", minimum=0.0, soft_max=1024.0,
            help="If above zero (and Resolution is 0), size this object's atlas from its surface area"),
    Setting("mode", str, "SCENE", "Mode", help="Where this object's samples live",
            choices=(("SCENE", "Scene", "The scene's mode"),
                     ("auto", "Auto", "Texture atlas, or vertex tables where the mesh is too dense or too big to "
                                      "unwrap")) + _MODE_CHOICES),
)


# The machine's settings (VisiBake's add-on preferences), used where an argument and the
# scene set nothing.
PREFERENCE_SETTINGS = _table(
    Setting("device", str, "auto", "Device", help="Where the transport passes (the gathers) run",
            choices=(("auto", "Auto", "The GPU passes on a real GPU; the CPU passes on a software renderer or "
                                      "without a GPU"),
                     ("gpu", "GPU", "Always run the transport passes on the GPU (Blender's gpu module)"),
                     ("cpu", "CPU", "Always run the transport passes on the CPU (compiled kernels)"))),
    Setting("cache_dir", str, "", "Cache Folder",
            help="Where visibility caches go when a scene sets no folder of its own (e.g. a fast disk); "
                 "empty: beside the saved .blend, else VisiBake's user folder"),
    Setting("cache_limit_mib", int, 10240, "Cache Limit (MiB)", minimum=0, soft_max=1048576,
            help="Most disk space a cache folder may take: before a table is written, the least recently used "
                 "cached tables in its folder are removed to make room, and a table larger than this is not "
                 "cached; 0: no limit"),
    Setting("default_preset", str, "NONE", "Default Preset",
            help="The preset a scene gets when VisiBake first sees it with no settings of its own (a new "
                 "file or scene, or a file saved without VisiBake); scenes with settings are never changed",
            choices=(("NONE", "None", f"New scenes start with VisiBake's built-in settings "
                                      f"({SETTINGS['directions'].default} directions, "
                                      f"{SETTINGS['bounces'].default} bounces, "
                                      f"{SETTINGS['resolution'].default} texels)"),
                     ("DRAFT", "Draft", "New scenes start with the Draft preset"),
                     ("PRODUCTION", "Production", "New scenes start with the Production preset"))),
    SETTINGS["threads"],
    Setting("resident_memory_mib", int, 2048, "Resident Memory (MiB)", minimum=0, soft_max=65536,
            help="Memory the last bake's preparation (samples and visibility table) may keep between bakes of "
                 "this session, so that a Relight with only lights or world changed reads nothing from disk; "
                 "0 keeps nothing"),
    Setting("gpu_memory_mib", int, 1024, "GPU Memory (MiB)", minimum=64, soft_max=16384,
            help="GPU memory the transport passes may use; the table is streamed in batches of directions "
                 "that fit"),
    Setting("cluster_workers", int, 0, "Cluster Workers", minimum=0, maximum=256, soft_max=64,
            help="Bake on this many local worker processes (a Dask cluster on this machine, started and "
                 "stopped with each Bake): the same images, with the visibility table traced, lit and read by "
                 "ranges of texels on the workers, for machines with many cores. Such a bake runs on the CPU, "
                 "without the cache or a later Relight; 0: bake in Blender's own process"),
)


def _default(name: str):
    return SETTINGS[name].default


class _Validated:
    """A dataclass of settings described in :data:`SETTINGS`, checked against it."""

    def validate(self) -> None:
        """Raise :class:`BakeRefused` (a ValueError) with a one-line reason for the first
        field that cannot work."""
        for field in fields(self):
            reason = SETTINGS[field.name].check(getattr(self, field.name))
            if reason is not None:
                raise BakeRefused(reason)


@dataclass
class BakeSettings(_Validated):
    """Everything that changes the result of a bake; each field is described by
    ``SETTINGS[name]``.

    shadows : 'fractions' (the paper: no ray at lighting time) or 'exact'
    shadow_regions : number of regions c_j for the fractions
    passes : output passes, a subset of PASSES
    light_groups : the groups sum to the combined pass
    vertex_lookup : 'interpolate' (barycentric mix of the triangle's three samples) or
        'nearest' (the paper's nearest vertex)
    """

    directions: int = _default("directions")
    bounces: int = _default("bounces")
    shadows: str = _default("shadows")
    shadow_regions: int = _default("shadow_regions")
    rotate: bool = _default("rotate")
    seed: int = _default("seed")
    interleave: int = _default("interleave")
    passes: tuple[str, ...] = _default("passes")
    margin: int = _default("margin")
    area_light_samples: int = _default("area_light_samples")
    footprint_samples: int = _default("footprint_samples")
    footprint_width: float = _default("footprint_width")
    sharp_contacts: bool = _default("sharp_contacts")
    stitch_seams: bool = _default("stitch_seams")
    emitter_samples: int = _default("emitter_samples")
    threads: int = _default("threads")
    chunk_rays: int = _default("chunk_rays")
    light_groups: bool = _default("light_groups")
    vertex_lookup: str = _default("vertex_lookup")
    target_error: float = _default("target_error")



@dataclass
class LayoutSettings(_Validated):
    """The scene's settings that decide where samples lie; an object's own
    (:data:`OBJECT_SETTINGS`) override them. Each field is described by ``SETTINGS[name]``.

    resolution : atlas width and height in texels
    texel_density : texels per unit of surface; above zero it sizes atlases instead of ``resolution``
    mode : one of LAYOUT_MODES
    """

    resolution: int = _default("resolution")
    texel_density: float = _default("texel_density")
    mode: str = _default("mode")



# The volume bake's settings (scene.visibake's Volumes section and ``visibake volume``).
VOLUME_SETTINGS = _table(
    Setting("volume_resolution", int, 64, "Resolution", minimum=2, maximum=1024, soft_max=256,
            help="Voxels along a volume's longest side; a finer grid is box-averaged down to it"),
    Setting("volume_directions", int, 64, "Directions", minimum=1, maximum=16384, soft_min=16, soft_max=1024,
            help="Global directions of the volume's scattering tables (one 3D table each)"),
    Setting("volume_bounces", int, 1, "Bounces", minimum=0, maximum=64, soft_max=8,
            help="Scattering bounces after the direct light (0: single scattering only)"),
    Setting("volume_points", int, 2, "Points per Ray", minimum=1, maximum=16, soft_max=4,
            help="Scattering points each table ray stores, stratified along it (more: less noise, more memory)"),
)


# The virtual gonioreflectometer (core.appearance): the panel's Materials from Micro-Geometry
# section and `visibake brdf` (whose options default to these).
APPEARANCE_SETTINGS = _table(
    Setting("appearance_lights", int, 100, "Light Directions", minimum=1, maximum=10000, soft_max=400,
            help="Light directions the tile's BRDF is sampled at, over the hemisphere (the sphere for a BSDF)"),
    Setting("appearance_views", int, 100, "View Directions", minimum=1, maximum=10000, soft_max=400,
            help="View directions for each light, over the hemisphere (the sphere for a BSDF)"),
    Setting("appearance_directions", int, 128, "Directions", minimum=8, maximum=4096, soft_max=1024,
            help="Global directions of the tile's visibility tables (the inter-reflections' quadrature)"),
    Setting("appearance_bounces", int, 2, "Bounces", minimum=0, maximum=64, soft_max=8,
            help="Inter-reflections within the micro-geometry after the direct light"),
    Setting("appearance_resolution", int, 64, "Resolution", minimum=1, maximum=2048, soft_max=256,
            help="Samples across the tile's period (its mesh is refined to this)"),
    Setting("appearance_format", str, "merl", "Format", help="The file the BRDF is written to",
            choices=(("merl", "MERL", "An isotropic MERL .binary table, as renderers' measured-BRDF readers take"),
                     ("table", "Table", "The light x view samples over the hemisphere and the transparency, "
                                        "as .npz (anisotropic tiles)"),
                     ("bsdf", "BSDF (Sphere)", "The light x view samples over the whole sphere, transmission "
                                               "included, as .npz (see-through and translucent tiles)"))),
    Setting("appearance_image_size", int, 256, "BTF Image Size", minimum=8, maximum=4096, soft_max=1024,
            help="Pixels a side of each BTF image (81 x 81 images, the tile rectified to texture space)"),
    Setting("appearance_image_format", str, "exr", "BTF Images", help="The file format of the BTF's images",
            choices=(("exr", "EXR", "Linear RGB, 32-bit float"), ("png", "PNG", "8-bit sRGB"))),
)

# Light fields (issue 19, core.lightfield): the panel's Light Field section and `visibake
# lightfield` (whose options default to these). The camera grid is the HCI benchmark's.
LIGHTFIELD_SETTINGS = _table(
    Setting("lightfield_columns", int, 9, "Views Across", minimum=1, maximum=64, soft_max=17,
            help="Columns of the grid of views (HCI's num_cams_x)"),
    Setting("lightfield_rows", int, 9, "Views Down", minimum=1, maximum=64, soft_max=17,
            help="Rows of the grid of views (HCI's num_cams_y)"),
    Setting("lightfield_baseline_mm", float, 50.0, "Baseline (mm)", minimum=0.001, maximum=1e6, soft_max=500.0,
            help="Distance between neighbouring views, in millimetres"),
    Setting("lightfield_focus_m", float, 2.0, "Focus Distance (m)", minimum=0.001, maximum=1e6, soft_max=100.0,
            help="Distance along the camera's axis where the views agree (zero disparity), in metres"),
    Setting("lightfield_width", int, 512, "View Width", minimum=8, maximum=8192, soft_max=2048,
            help="Pixels across each view"),
    Setting("lightfield_height", int, 512, "View Height", minimum=8, maximum=8192, soft_max=2048,
            help="Pixels down each view"),
    Setting("lightfield_supersampling", int, 3, "Supersamples", minimum=1, maximum=4,
            help="Samples per pixel along each axis, filtered as Cycles' default pixel filter: 3 is the closest "
                 "to Cycles' anti-aliasing; 2 renders about 1.5x faster, 1 about 2.5x (aliased edges)"),
    Setting("lightfield_format", str, "hci", "Layout", help="How the views are laid out in the folder",
            choices=(("hci", "HCI", "input_CamNNN.png/.exr, parameters.cfg and the centre view's depth and "
                                    "disparity (the HCI 4D light field benchmark)"),
                     ("stanford", "Stanford", "out_RR_CC_Y_X_.png rectified views (the Stanford light field "
                                              "archive), with the same parameters and ground truth"))),
)
