"""The settings model: scene settings (scene.visibake) and per-object settings.

Each property's title, default, limits, choices and tooltip come from its
core.settings.Setting (SETTINGS, OBJECT_SETTINGS); only its name, its update
function and how the UI shows it are chosen here. The names are what saved .blend
files store: never rename one.
"""
import bpy

from ..core.settings import (
    APPEARANCE_SETTINGS,
    LIGHTFIELD_SETTINGS,
    OBJECT_SETTINGS,
    PRESETS,
    SETTINGS,
    VOLUME_SETTINGS,
    Setting,
)


def setting_property(spec: Setting, **options):
    """The Blender property of ``spec``; ``options`` adds to or overrides its keywords."""
    keywords = {"name": spec.title, "description": spec.help}
    if spec.type is tuple:
        keywords.update(items=list(spec.choices), default=set(spec.default), options={"ENUM_FLAG"})
        return bpy.props.EnumProperty(**{**keywords, **options})
    if spec.choices:
        keywords.update(items=list(spec.choices), default=spec.default)
        return bpy.props.EnumProperty(**{**keywords, **options})
    keywords["default"] = spec.default
    if spec.type is bool:
        return bpy.props.BoolProperty(**{**keywords, **options})
    if spec.type is str:
        return bpy.props.StringProperty(**{**keywords, **options})
    for key, value in (("min", spec.minimum), ("max", spec.maximum), ("soft_min", spec.soft_min),
                       ("soft_max", spec.soft_max)):
        if value is not None:
            keywords[key] = value
    prop = {int: bpy.props.IntProperty, float: bpy.props.FloatProperty}[spec.type]
    return prop(**{**keywords, **options})


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
    preset: setting_property(SETTINGS["preset"], update=_apply_preset)
    directions: setting_property(SETTINGS["directions"], update=_mark_custom)
    target_error: setting_property(SETTINGS["target_error"], subtype="FACTOR")
    chosen_directions: setting_property(SETTINGS["chosen_directions"])
    bounces: setting_property(SETTINGS["bounces"], update=_mark_custom)
    shadows: setting_property(SETTINGS["shadows"], update=_mark_custom)
    passes: setting_property(SETTINGS["passes"])
    resolution: setting_property(SETTINGS["resolution"], update=_mark_custom)
    texel_density: setting_property(SETTINGS["texel_density"])
    mode: setting_property(SETTINGS["mode"])
    bake_all: setting_property(SETTINGS["bake_all"])
    rotate: setting_property(SETTINGS["rotate"], update=_mark_custom)
    seed: setting_property(SETTINGS["seed"])
    interleave: setting_property(SETTINGS["interleave"])
    margin: setting_property(SETTINGS["margin"])
    footprint_samples: setting_property(SETTINGS["footprint_samples"])
    sharp_contacts: setting_property(SETTINGS["sharp_contacts"])
    stitch_seams: setting_property(SETTINGS["stitch_seams"])
    use_cache: setting_property(SETTINGS["use_cache"])
    cache_dir: setting_property(SETTINGS["cache_dir"], subtype="DIR_PATH")
    light_groups: setting_property(SETTINGS["light_groups"])
    vertex_lookup: setting_property(SETTINGS["vertex_lookup"])
    refine_vertex_objects: setting_property(SETTINGS["refine_vertex_objects"])
    # The row of the objects list that is selected: the list's state, not a setting.
    active_object_index: bpy.props.IntProperty(
        name="Active Object", default=0, min=0,
        description="The row of the objects list that is selected (the list's own state)")
    output_dir: setting_property(SETTINGS["output_dir"], subtype="DIR_PATH")
    volume_resolution: setting_property(VOLUME_SETTINGS["volume_resolution"])
    volume_directions: setting_property(VOLUME_SETTINGS["volume_directions"])
    volume_bounces: setting_property(VOLUME_SETTINGS["volume_bounces"])
    volume_points: setting_property(VOLUME_SETTINGS["volume_points"])
    appearance_lights: setting_property(APPEARANCE_SETTINGS["appearance_lights"])
    appearance_views: setting_property(APPEARANCE_SETTINGS["appearance_views"])
    appearance_directions: setting_property(APPEARANCE_SETTINGS["appearance_directions"])
    appearance_bounces: setting_property(APPEARANCE_SETTINGS["appearance_bounces"])
    appearance_resolution: setting_property(APPEARANCE_SETTINGS["appearance_resolution"])
    appearance_format: setting_property(APPEARANCE_SETTINGS["appearance_format"])
    appearance_image_size: setting_property(APPEARANCE_SETTINGS["appearance_image_size"])
    appearance_image_format: setting_property(APPEARANCE_SETTINGS["appearance_image_format"])
    lightfield_columns: setting_property(LIGHTFIELD_SETTINGS["lightfield_columns"])
    lightfield_rows: setting_property(LIGHTFIELD_SETTINGS["lightfield_rows"])
    lightfield_baseline_mm: setting_property(LIGHTFIELD_SETTINGS["lightfield_baseline_mm"])
    lightfield_focus_m: setting_property(LIGHTFIELD_SETTINGS["lightfield_focus_m"])
    lightfield_width: setting_property(LIGHTFIELD_SETTINGS["lightfield_width"])
    lightfield_height: setting_property(LIGHTFIELD_SETTINGS["lightfield_height"])
    lightfield_supersampling: setting_property(LIGHTFIELD_SETTINGS["lightfield_supersampling"])
    lightfield_format: setting_property(LIGHTFIELD_SETTINGS["lightfield_format"])


class VisiBakeObjectSettings(bpy.types.PropertyGroup):
    role: setting_property(OBJECT_SETTINGS["role"])
    resolution: setting_property(OBJECT_SETTINGS["resolution"])
    texel_density: setting_property(OBJECT_SETTINGS["texel_density"])
    mode: setting_property(OBJECT_SETTINGS["mode"])

    def effective_mode(self, scene_settings) -> str:
        return scene_settings.mode if self.mode == "SCENE" else self.mode


classes = (VisiBakeSceneSettings, VisiBakeObjectSettings)


def register_properties():
    bpy.types.Scene.visibake = bpy.props.PointerProperty(type=VisiBakeSceneSettings)
    bpy.types.Object.visibake = bpy.props.PointerProperty(type=VisiBakeObjectSettings)


def unregister_properties():
    del bpy.types.Object.visibake
    del bpy.types.Scene.visibake
