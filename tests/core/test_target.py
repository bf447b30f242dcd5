"""The direction count a bake at a Target Error chooses from its pilot (core.pipeline.target)."""
import numpy as np
import pytest

from core.pipeline.relight import bake
from core.pipeline.target import AIM, DIRECTION_STEPS, GATHER_ERROR_EXPONENT, choose_directions
from core.pipeline.transport import BOUNCE_SHARE_OF_TARGET
from core.scene import Light, Material, Scene
from core.settings import BakeSettings
from core_scenes import box_interior


def _estimate(lamps, gathered):
    return {"total": (lamps ** 2 + gathered ** 2) ** 0.5, "lamps": lamps, "gathered": gathered}


def test_a_pilot_within_the_target_is_the_bake():
    choice = choose_directions(_estimate(0.005, 0.02), 64, 0.03)
    assert choice.directions == choice.pilot_directions == 64 and "within the target" in choice.reason


def test_more_directions_bring_the_gathered_light_within_what_the_lamps_leave():
    estimate = _estimate(0.01, 0.06)
    choice = choose_directions(estimate, 64, 0.03)
    aim = AIM * 0.03
    # The smallest step whose predicted error is within the aim; the step before it is not.
    assert choice.directions in DIRECTION_STEPS and choice.directions > 64
    assert choice.predicted <= aim

    def predicted(count):
        return (0.01 ** 2 + (0.06 * (64 / count) ** GATHER_ERROR_EXPONENT) ** 2) ** 0.5

    before = DIRECTION_STEPS[DIRECTION_STEPS.index(choice.directions) - 1]
    assert predicted(choice.directions) == pytest.approx(choice.predicted) and predicted(before) > aim
    assert choice.as_dict()["pilot_estimate"] is estimate


def test_lamps_whose_error_alone_exceeds_the_target_bring_the_gathered_light_to_their_level_and_say_why():
    # The gathered light above the lamps' error: brought to it (64 (0.06 / 0.04)^2 = 144: 192).
    choice = choose_directions(_estimate(0.04, 0.06), 64, 0.03)
    assert choice.directions == 192 and "alone exceeds" in choice.reason
    # Already below it: more directions buy nothing, the pilot stays.
    choice = choose_directions(_estimate(0.04, 0.03), 64, 0.03)
    assert choice.directions == 64 and "alone exceeds" in choice.reason


def test_the_choice_stops_at_the_most_it_may_take():
    choice = choose_directions(_estimate(0.0, 0.5), 64, 0.01, most=512)
    assert choice.directions == 512 and "the most this bake chooses" in choice.reason


def test_without_an_estimate_the_pilot_is_kept():
    for estimate in (None, {"total": None, "lamps": None, "gathered": None}):
        choice = choose_directions(estimate, 96, 0.03)
        assert choice.directions == 96 and "no estimate" in choice.reason


def test_at_a_target_the_bounces_that_add_less_than_its_share_are_not_gathered():
    def room(target):
        box = box_interior(size=2.0, material=Material(base_color=np.full(3, 0.5)), resolution=16)
        lamp = Light("Lamp", "POINT", np.ones(3), 200.0, position=np.array([0.2, 0.1, 0.3]))
        result = bake(Scene([box], [lamp]), BakeSettings(directions=64, bounces=8, target_error=target))
        return result.objects[0].images["lighting"], result.report

    every, report = room(0.0)
    assert report["gathers"] == 8
    fewer, report = room(0.05)
    stop = next(s for s in report["skipped"] if "below the Target Error" in s)
    assert 3 <= report["gathers"] < 8, stop
    covered = every[..., 3] > 0
    # What the bounces left out carried (albedo 0.5: each about half the one before) is within their share.
    missing = 1.0 - fewer[covered][:, :3].mean() / every[covered][:, :3].mean()
    print(f"\n{report['gathers']} of 8 bounces; {missing:.3%} of the light left out ({stop})")
    assert 0.0 <= missing < 2 * BOUNCE_SHARE_OF_TARGET * 0.05
