"""core.settings: the one table of settings, its defaults, and the one validation."""
import dataclasses
import math

import pytest

from core.errors import BakeRefused
from core.settings import (
    LAYOUT_MODES,
    OBJECT_SETTINGS,
    PASSES,
    PREFERENCE_SETTINGS,
    PRESETS,
    SETTINGS,
    SHADOW_MODES,
    VERTEX_LOOKUPS,
    BakeSettings,
    LayoutSettings,
)

TABLES = {"SETTINGS": SETTINGS, "OBJECT_SETTINGS": OBJECT_SETTINGS, "PREFERENCE_SETTINGS": PREFERENCE_SETTINGS}
ALL_SPECS = [(table, spec) for table, specs in TABLES.items() for spec in specs.values()]
DATACLASSES = (BakeSettings, LayoutSettings)
FIELDS = [(cls, field.name) for cls in DATACLASSES for field in dataclasses.fields(cls)]


def _below(spec):
    return spec.minimum - 1 if spec.type is int else spec.minimum - 0.5


@pytest.mark.parametrize("table, spec", ALL_SPECS, ids=[f"{t}.{s.name}" for t, s in ALL_SPECS])
def test_every_default_passes_its_own_check(table, spec):
    assert spec.check(spec.default) is None
    assert spec.help and spec.title
    if spec.choices:
        assert all(len(choice) == 3 and all(choice) for choice in spec.choices), "a choice without title or help"
    if spec.minimum is not None and spec.soft_min is not None:
        assert spec.soft_min >= spec.minimum


def test_the_default_settings_validate():
    BakeSettings().validate()
    LayoutSettings().validate()


@pytest.mark.parametrize("cls, name", FIELDS, ids=[f"{c.__name__}.{n}" for c, n in FIELDS])
def test_each_field_s_default_is_its_setting_s(cls, name):
    assert getattr(cls(), name) == SETTINGS[name].default


def test_the_report_s_settings_keep_their_keys():
    # asdict(BakeSettings) is the report's "settings": its keys are part of the JSON.
    assert list(dataclasses.asdict(BakeSettings())) == [
        "directions", "bounces", "shadows", "shadow_regions", "rotate", "seed", "interleave", "passes", "margin",
        "area_light_samples", "footprint_samples", "footprint_width", "sharp_contacts", "stitch_seams",
        "emitter_samples", "threads", "chunk_rays", "light_groups", "vertex_lookup", "target_error"]


def test_the_choices_are_core_s_constants():
    assert SETTINGS["shadows"].values == SHADOW_MODES
    assert SETTINGS["vertex_lookup"].values == VERTEX_LOOKUPS
    assert SETTINGS["passes"].values == PASSES
    assert SETTINGS["mode"].values == LAYOUT_MODES
    assert OBJECT_SETTINGS["mode"].values == ("SCENE",) + LAYOUT_MODES
    assert set(PRESETS) < set(SETTINGS["preset"].values)
    assert set(PRESETS) < set(PREFERENCE_SETTINGS["default_preset"].values)


@pytest.mark.parametrize("preset", sorted(PRESETS))
def test_every_preset_sets_valid_values_and_describes_them(preset):
    values = PRESETS[preset]
    BakeSettings(**{k: v for k, v in values.items() if k in SETTINGS and k != "resolution"}).validate()
    LayoutSettings(resolution=values["resolution"]).validate()
    described = dict((v, h) for v, _, h in SETTINGS["preset"].choices)[preset]
    assert described.startswith(f"{values['directions']} directions, {values['bounces']} bounce")
    assert f"{values['resolution']} texels" in described


LIMITED = [(cls, name) for cls, name in FIELDS if SETTINGS[name].minimum is not None]


@pytest.mark.parametrize("cls, name", LIMITED, ids=[f"{c.__name__}.{n}" for c, n in LIMITED])
def test_a_value_below_its_minimum_is_refused_naming_the_setting(cls, name):
    spec = SETTINGS[name]
    cls(**{name: spec.minimum}).validate()  # the limit itself is allowed
    with pytest.raises(BakeRefused, match=f"^{name.replace('_', ' ')} must be >= {spec.minimum}"):
        cls(**{name: _below(spec)}).validate()


def test_a_float_that_is_not_a_number_is_refused():
    with pytest.raises(BakeRefused, match="texel density"):
        LayoutSettings(texel_density=math.nan).validate()


@pytest.mark.parametrize("changes, message", [
    # The messages of BakeSettings.validate before the table existed, word for word.
    ({"directions": 0}, "directions must be >= 1, got 0"),
    ({"bounces": -1}, "bounces must be >= 0, got -1"),
    ({"shadows": "soft"}, "shadows must be one of fractions, exact, got 'soft'"),
    ({"shadow_regions": 0}, "shadow regions must be >= 1, got 0"),
    ({"passes": ()}, "passes: choose at least one of lighting, direct, indirect, irradiance, ao"),
    ({"passes": ("lighting", "shine")},
     "passes: choose at least one of lighting, direct, indirect, irradiance, ao (unknown: shine)"),
    ({"margin": -1}, "margin must be >= 0, got -1"),
    ({"area_light_samples": 0}, "area light samples must be >= 1"),
    ({"emitter_samples": 0}, "emitter samples must be >= 1"),
    ({"vertex_lookup": "far"}, "vertex lookup must be one of interpolate, nearest, got 'far'"),
])
def test_the_refusals_say_what_they_said(changes, message):
    with pytest.raises(BakeRefused) as refused:
        BakeSettings(**changes).validate()
    assert str(refused.value) == message


def test_the_first_bad_field_is_the_one_refused():
    with pytest.raises(BakeRefused, match="^bounces"):
        BakeSettings(bounces=-1, margin=-1).validate()


@pytest.mark.parametrize("changes, message", [
    ({"resolution": 0}, "resolution must be >= 1, got 0"),
    ({"texel_density": -2.0}, "texel density must be >= 0.0, got -2.0"),
    ({"mode": "pixels"}, "mode must be one of auto, atlas, vertex, got 'pixels'"),
])
def test_layout_settings_are_refused_like_bake_settings(changes, message):
    with pytest.raises(BakeRefused) as refused:
        LayoutSettings(**changes).validate()
    assert str(refused.value) == message


def test_a_front_end_names_the_value_its_own_way():
    assert SETTINGS["directions"].check(0, "--directions") == "--directions must be >= 1, got 0"
    assert SETTINGS["passes"].check(("shine",), "--passes").startswith("--passes: choose at least one of")
    assert SETTINGS["directions"].check(1, "--directions") is None
    assert PREFERENCE_SETTINGS["device"].check("tpu") == "device must be one of auto, gpu, cpu, got 'tpu'"


def test_the_scene_holds_exactly_the_settings_marked_so():
    # Mirrors panels/properties.py: what a scene stores besides the list's UI state.
    on_scene = {name for name, spec in SETTINGS.items() if spec.on_scene}
    assert on_scene == {"preset", "directions", "bounces", "shadows", "passes", "resolution", "texel_density", "mode",
                        "bake_all", "rotate", "seed", "margin", "footprint_samples",
                        "sharp_contacts", "stitch_seams", "interleave", "use_cache", "cache_dir", "light_groups",
                        "vertex_lookup", "refine_vertex_objects", "output_dir", "target_error",
                        "chosen_directions"}
