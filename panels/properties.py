"""The settings model: scene settings (scene.visibake) and per-object settings."""
import bpy

from ..core.settings import BakeSettings, PASSES

_PASS_ITEMS = [(p, p.capitalize(), f"Write the {p} pass") for p in PASSES]

# What each preset sets; any later change to one of these makes the preset Custom.
PRESETS = {
    "DRAFT": {"directions": 64, "bounces": 1, "resolution": 128, "shadows": "exact", "rotate": False},
    "PRODUCTION": {"directions": 256, "bounces": 3, "resolution": 512, "shadows": "exact", "rotate": True},
}
_applying_preset = False


def _apply_preset(settings, context) -> None:
    global _applying_preset
    values = PRESETS.get(settings.preset)
    if values is None:
        return
    _applying_preset = True
    try:
        for name, value in values.items():
            setattr(settings, name, value)
    finally:
        _applying_preset = False


def _mark_custom(settings, context) -> None:
    """A setting changed by hand: the preset no longer describes the settings."""
    if _applying_preset or settings.preset == "CUSTOM":
        return
    values = PRESETS.get(settings.preset, {})
    if any(getattr(settings, name) != value for name, value in values.items()):
        settings.preset = "CUSTOM"


def settings_untouched(settings) -> bool:
    """True for VisiBake settings nobody has set yet: a new scene, or a file saved without VisiBake."""
    return not any(settings.is_property_set(name) for name in settings.bl_rna.properties.keys()
                   if name != "rna_type")


def apply_default_preset(scene, preset: str) -> bool:
    """Give an untouched scene the preferred preset; True if it did.

    Scenes whose settings anybody has set (VisiBake's or the user's) are never changed.
    """
    if preset not in PRESETS or not settings_untouched(scene.visibake):
        return False
    scene.visibake.preset = preset
    return True


class VisiBakeSceneSettings(bpy.types.PropertyGroup):
    preset: bpy.props.EnumProperty(
        name="Preset", default="CUSTOM", update=_apply_preset,
        items=[("DRAFT", "Draft", "64 directions, 1 bounce, 128 texels, exact shadows: a quick look"),
               ("PRODUCTION", "Production", "256 directions, 3 bounces, 512 texels, exact shadows, rotated "
                                            "direction set: final quality"),
               ("CUSTOM", "Custom", "The settings below as they are")],
        description="Set directions, bounces, resolution and shadows together")
    directions: bpy.props.IntProperty(
        name="Directions", default=128, min=1, soft_min=16, soft_max=1024, update=_mark_custom,
        description="Size of the global direction set: rays per texel for visibility (more: less noise, slower)")
    bounces: bpy.props.IntProperty(
        name="Bounces", default=2, min=0, soft_max=8, update=_mark_custom,
        description="Diffuse bounces of indirect light (as Cycles' Diffuse bounces)")
    shadows: bpy.props.EnumProperty(
        name="Shadows", default="exact", update=_mark_custom,
        items=[("fractions", "Fractions", "Shadows from the precomputed visibility (no ray at lighting time, soft)"),
               ("exact", "Exact", "One shadow ray per texel and light (sharp, traced at every bake)")],
        description="How direct light is shadowed")
    passes: bpy.props.EnumProperty(
        name="Passes", options={"ENUM_FLAG"}, items=_PASS_ITEMS, default={"lighting"},
        description="Which passes to write")
    resolution: bpy.props.IntProperty(
        name="Resolution", default=256, min=1, soft_min=16, soft_max=4096, update=_mark_custom,
        description="Atlas width and height in texels for objects without their own resolution")
    texel_density: bpy.props.FloatProperty(
        name="Texels per Unit", default=0.0, min=0.0, soft_max=1024.0,
        description="If above zero, size each atlas from the object's surface area instead of Resolution")
    mode: bpy.props.EnumProperty(
        name="Mode", default="auto",
        items=[("auto", "Auto", "Texture atlas; vertex tables for meshes too dense or too big to unwrap, "
                "or where unwrapping fails"),
               ("atlas", "Atlas", "Texture atlas (UV map), results as images"),
               ("vertex", "Vertex", "Per-vertex tables, results as colour attributes VB_<pass>")],
        description="Where samples live")
    bake_all: bpy.props.BoolProperty(
        name="All Objects", default=False,
        description="Bake every visible mesh object instead of the selected ones")
    rotate: bpy.props.BoolProperty(
        name="Rotate Directions", default=False, update=_mark_custom,
        description="Randomly rotate the direction set (seeded): structured artefacts become noise")
    seed: bpy.props.IntProperty(name="Seed", default=0, min=0, description="Seed of the direction rotation")
    margin: bpy.props.IntProperty(
        name="Margin", default=4, min=0, soft_max=32,
        description="Texels the results are extended into the gutter so filtering never pulls in black")
    use_cache: bpy.props.BoolProperty(
        name="Cache Visibility", default=True,
        description="Keep the visibility tables on disk, so bakes after changes to lights, materials or the world "
                    "(and Relight) skip the visibility stage")
    cache_dir: bpy.props.StringProperty(
        name="Cache Folder", subtype="DIR_PATH", default="",
        description="Where the visibility cache lives; empty: a visibake_cache folder beside the saved .blend, "
                    "else VisiBake's folder in your user profile")
    light_groups: bpy.props.BoolProperty(
        name="Light Groups", default=False,
        description="Also write every lighting pass per light group (a lamp's Light Group, else each lamp; the world; "
                    "each emitting object), so lights can be re-mixed without another bake")
    vertex_lookup: bpy.props.EnumProperty(
        name="Vertex Lookup", default="interpolate",
        items=[("interpolate", "Interpolate", "Mix the three vertices of the triangle a ray lands on"),
               ("nearest", "Nearest", "The paper's variant: the nearest vertex of that triangle")],
        description="How light is read where a ray lands on a vertex-mode object")
    refine_vertex_objects: bpy.props.BoolProperty(
        name="Refine Coarse Vertex Objects", default=False,
        description="Where a vertex-mode object's triangles are too large for its light (a shadow edge inside "
                    "them), bake a copy with those faces subdivided in its place and hide the original; your mesh "
                    "is never changed")
    active_object_index: bpy.props.IntProperty(
        name="Active Object", default=0, min=0,
        description="The row of the objects list that is selected (the list's own state)")
    output_dir: bpy.props.StringProperty(
        name="Output Folder", subtype="DIR_PATH", default="",
        description="Folder for the EXR files (<folder>/<object>/<pass>.exr); empty: images in the .blend only")

    def to_bake_settings(self, threads: int = 0) -> BakeSettings:
        return BakeSettings(directions=self.directions, bounces=self.bounces, shadows=self.shadows,
                            rotate=self.rotate, seed=self.seed, margin=self.margin,
                            passes=tuple(p for p in PASSES if p in self.passes), light_groups=self.light_groups,
                            vertex_lookup=self.vertex_lookup, threads=threads)


class VisiBakeObjectSettings(bpy.types.PropertyGroup):
    role: bpy.props.EnumProperty(
        name="Role", default="INCLUDE",
        items=[("INCLUDE", "Bake", "Bake this object when it is selected, or with All Objects"),
               ("OCCLUDE", "Occlude Only", "Never bake this object: it only casts shadows and reflects light")],
        description="Whether this object gets results or only takes part in the light transport")
    resolution: bpy.props.IntProperty(
        name="Resolution", default=0, min=0, soft_max=4096,
        description="Atlas size of this object in texels (0: the scene's setting)")
    texel_density: bpy.props.FloatProperty(
        name="Texels per Unit", default=0.0, min=0.0, soft_max=1024.0,
        description="If above zero (and Resolution is 0), size this object's atlas from its surface area")
    mode: bpy.props.EnumProperty(
        name="Mode", default="SCENE",
        items=[("SCENE", "Scene", "The scene's mode"),
               ("auto", "Auto", "Texture atlas, or vertex tables where the mesh is too dense or too big to unwrap"),
               ("atlas", "Atlas", "Texture atlas (UV map), results as images"),
               ("vertex", "Vertex", "Per-vertex tables, results as colour attributes VB_<pass>")],
        description="Where this object's samples live")

    def effective_mode(self, scene_settings) -> str:
        return scene_settings.mode if self.mode == "SCENE" else self.mode


classes = (VisiBakeSceneSettings, VisiBakeObjectSettings)


def register_properties():
    bpy.types.Scene.visibake = bpy.props.PointerProperty(type=VisiBakeSceneSettings)
    bpy.types.Object.visibake = bpy.props.PointerProperty(type=VisiBakeObjectSettings)


def unregister_properties():
    del bpy.types.Object.visibake
    del bpy.types.Scene.visibake
