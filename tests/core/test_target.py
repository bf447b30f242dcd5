"""The direction count a bake at a Target Error chooses from its pilot (core.pipeline.target)."""
import pytest

from core.pipeline.target import AIM, DIRECTION_STEPS, GATHER_ERROR_EXPONENT, choose_directions


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


def test_lamps_whose_error_alone_exceeds_the_target_keep_the_pilot_and_say_why():
    choice = choose_directions(_estimate(0.04, 0.06), 64, 0.03)
    assert choice.directions == 64 and "alone exceeds" in choice.reason


def test_the_choice_stops_at_the_most_it_may_take():
    choice = choose_directions(_estimate(0.0, 0.5), 64, 0.01, most=512)
    assert choice.directions == 512 and "the most this bake chooses" in choice.reason


def test_without_an_estimate_the_pilot_is_kept():
    for estimate in (None, {"total": None, "lamps": None, "gathered": None}):
        choice = choose_directions(estimate, 96, 0.03)
        assert choice.directions == 96 and "no estimate" in choice.reason
