"""The panels' draw code, the tooltips, and the preferences, as far as background mode allows.

Background mode never makes a ``bpy.types.UILayout``, so the draw functions are given a
stand-in that checks every call against the real UILayout RNA: the function exists,
every argument is one of its parameters and the required ones are there, the icon is
one of Blender's, the property exists on the data, the operator is registered and its
properties are real. A typo in any draw code fails here. What it cannot check is how
the panel looks.
"""
import json

import bpy

import pytest

from bpy_scenes import ground_block_lamp

_LAYOUT_RNA = bpy.types.UILayout.bl_rna
_ICONS = set(_LAYOUT_RNA.functions["prop"].parameters["icon"].enum_items.keys())
_SUBLAYOUTS = {"row", "column", "box", "split", "column_flow", "grid_flow"}


def _operator_rna(idname: str):
    module, name = idname.split(".")
    return getattr(getattr(bpy.ops, module), name).get_rna_type()  # raises KeyError if not registered


class _OperatorProperties:
    def __init__(self, idname):
        object.__setattr__(self, "_names", set(_operator_rna(idname).properties.keys()))

    def __setattr__(self, name, value):
        assert name in self._names, f"operator has no property {name!r}"


class CheckedLayout:
    """A UILayout stand-in that checks each call and records what would be drawn."""

    def __init__(self, drawn: list):
        object.__setattr__(self, "drawn", drawn)

    def __setattr__(self, name, value):
        assert name in _LAYOUT_RNA.properties, f"UILayout has no attribute {name!r}"

    def __getattr__(self, name):
        function = _LAYOUT_RNA.functions.get(name)
        assert function is not None, f"UILayout has no function {name!r}"
        inputs = [p for p in function.parameters if not p.is_output]

        def call(*args, **kwargs):
            names = [p.identifier for p in inputs]
            assert len(args) <= len(names), f"{name}: too many arguments"
            bound = dict(zip(names, args))
            unknown = set(kwargs) - set(names)
            assert not unknown, f"{name}: no parameters {unknown}"
            bound.update(kwargs)
            missing = [p.identifier for p in inputs if p.is_required and p.identifier not in bound]
            assert not missing, f"{name}: missing {missing}"
            if "icon" in bound:
                assert bound["icon"] in _ICONS, f"{name}: no icon {bound['icon']!r}"
            if name == "prop":
                assert bound["property"] in bound["data"].bl_rna.properties, f"no property {bound['property']!r}"
                bound["owner"] = bound["data"].bl_rna.identifier
            if name == "template_list":
                assert hasattr(bpy.types, bound["listtype_name"]), f"no list type {bound['listtype_name']!r}"
                assert bound["propname"] in bound["dataptr"].bl_rna.properties
                assert bound["active_propname"] in bound["active_dataptr"].bl_rna.properties
            self.drawn.append((name, {k: v for k, v in bound.items() if isinstance(v, (str, int, float))}))
            if name in _SUBLAYOUTS:
                return CheckedLayout(self.drawn)
            if name == "operator":
                return _OperatorProperties(bound["operator"])
            return None

        return call


def _draw(panel_class, context=None):
    drawn = []
    panel = type("PanelStandIn", (), {"layout": CheckedLayout(drawn)})()
    panel_class.draw(panel, context or bpy.context)
    return drawn


def _props(drawn):
    return [options["property"] for name, options in drawn if name == "prop"]


def _operators(drawn):
    return [options["operator"] for name, options in drawn if name == "operator"]


def _labels(drawn):
    return [options.get("text", "") for name, options in drawn if name == "label"]


@pytest.fixture
def scene(clean_scene):
    ground, block = ground_block_lamp()
    bpy.context.view_layer.objects.active = block
    return ground, block


def test_the_main_panel_draws_every_setting_the_buttons_and_the_cache(visibake, scene, tmp_path):
    main = visibake.panels.main
    bpy.context.scene.visibake.cache_dir = str(tmp_path / "cache")
    bpy.context.view_layer.update()  # as the UI does after a change: the cache status follows outside draw
    drawn = _draw(main.VIEW3D_PT_visibake)
    settings = set(bpy.context.scene.visibake.bl_rna.properties.keys()) - {"rna_type", "name", "active_object_index"}
    volumes = _draw(main.VIEW3D_PT_visibake_volumes)
    appearance = _draw(main.VIEW3D_PT_visibake_appearance)
    lightfield = _draw(main.VIEW3D_PT_visibake_lightfield)
    # Every scene setting is on the panel.
    assert settings <= set(_props(drawn)) | set(_props(volumes)) | set(_props(appearance)) | set(_props(lightfield))
    assert {p for p in settings if p.startswith("lightfield_")} == set(_props(lightfield))
    assert _operators(lightfield) == ["visibake.render_lightfield"]
    assert {p for p in settings if p.startswith("volume_")} == set(_props(volumes))  # the volumes' in their section
    assert _operators(volumes) == ["visibake.bake_volume"]
    assert {p for p in settings if p.startswith("appearance_")} == set(_props(appearance))
    assert _operators(appearance) == ["visibake.simulate_brdf", "visibake.simulate_btf"]
    active_object = {options["property"] for name, options in drawn
                     if name == "prop" and options["owner"] == "VisiBakeObjectSettings"}
    device = [options["property"] for name, options in drawn
              if name == "prop" and options["owner"] == "VisiBakePreferences"]
    assert device == ["device", "cluster_workers"]  # preferences, shown where the bake is set up
    assert active_object == {"role", "resolution", "mode", "texel_density"}  # and the active object's own
    assert {"visibake.bake", "visibake.relight", "visibake.preview_add", "visibake.preview_remove",
            "visibake.clear_cache"} <= set(_operators(drawn))
    assert any(text.startswith("Cache: no table for these settings") for text in _labels(drawn))

    bpy.context.scene.visibake.use_cache = False
    drawn = _draw(main.VIEW3D_PT_visibake)
    assert "visibake.clear_cache" not in _operators(drawn) and "cache_dir" not in _props(drawn)


def test_after_a_bake_the_panel_shows_the_cache_and_the_last_bake(visibake, scene, tmp_path):
    main = visibake.panels.main
    bpy.context.scene.visibake.cache_dir = str(tmp_path / "cache")
    assert not main.VIEW3D_PT_visibake_report.poll(bpy.context)
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    labels = _labels(_draw(main.VIEW3D_PT_visibake))
    assert any(text.startswith("Cache: valid for the scene as it is") for text in labels)
    assert any(text.startswith("VisiBake: baked 2 object(s)") for text in labels)
    assert main.VIEW3D_PT_visibake_report.poll(bpy.context)
    report = json.loads(bpy.context.scene["visibake_report"])
    labels = _labels(_draw(main.VIEW3D_PT_visibake_report))
    assert labels == [text for text, _ in main.report_lines(report)]
    assert any(text.startswith("cache: miss") for text in labels)

    scene[0].location.x += 0.25
    bpy.context.view_layer.update()
    labels = _labels(_draw(main.VIEW3D_PT_visibake))
    assert any(text.startswith("Cache: stale") for text in labels) and "changed: Ground" in labels

    bpy.context.scene["visibake_report"] = "{not json"
    assert _labels(_draw(main.VIEW3D_PT_visibake_report)) == ["The last report cannot be read"]


def test_the_objects_list_shows_meshes_with_their_role_mode_and_resolution(visibake, scene):
    main = visibake.panels.main
    drawn = _draw(main.VIEW3D_PT_visibake_objects)
    assert [name for name, _ in drawn] == ["template_list"]
    drawn = []
    ground, block = scene
    lamp = bpy.data.objects["Lamp"]
    ui_list = type("ListStandIn", (), {"bitflag_filter_item": 1 << 30})()
    main.VISIBAKE_UL_objects.draw_item(ui_list, bpy.context, CheckedLayout(drawn), bpy.context.scene, block, 0,
                                       bpy.context.scene.visibake, "active_object_index")
    assert _props(drawn) == ["role", "mode", "resolution", "texel_density"] and _labels(drawn) == ["Block"]
    flags, order = main.VISIBAKE_UL_objects.filter_items(ui_list, bpy.context, bpy.context.scene, "objects")
    shown = [obj.name for obj, flag in zip(bpy.context.scene.objects, flags) if flag]
    assert sorted(shown) == ["Block", "Ground"] and lamp.name not in shown and order == []


def test_the_preferences_draw_every_preference(visibake, clean_scene):
    prefs = visibake.operators.adapter.device.preferences()
    drawn = []
    stand_in = type("PrefsStandIn", (), {"layout": CheckedLayout(drawn),
                                         "__getattr__": lambda self, name: getattr(prefs, name)})()
    type(prefs).draw(stand_in, bpy.context)
    assert set(_props(drawn)) == set(prefs.bl_rna.properties.keys()) - {"rna_type", "bl_idname"}


def test_every_operator_setting_and_choice_has_a_tooltip(visibake):
    operators = [cls for cls in visibake.operators.classes if issubclass(cls, bpy.types.Operator)]
    assert {cls.bl_idname for cls in operators} >= {"visibake.bake", "visibake.relight", "visibake.preview_add",
                                                    "visibake.preview_remove", "visibake.clear_cache"}
    for cls in operators:
        assert len(_operator_rna(cls.bl_idname).description) > 20, cls.bl_idname
    groups = [bpy.types.Scene.bl_rna.properties["visibake"].fixed_type,
              bpy.types.Object.bl_rna.properties["visibake"].fixed_type,
              visibake.operators.adapter.device.preferences().bl_rna]
    for group in groups:
        for prop in group.properties:
            if prop.identifier in ("rna_type", "name", "bl_idname"):
                continue
            assert len(prop.description) > 10, f"{group.identifier}.{prop.identifier}"
            for item in getattr(prop, "enum_items", []):
                assert item.description, f"{group.identifier}.{prop.identifier}: {item.identifier}"
