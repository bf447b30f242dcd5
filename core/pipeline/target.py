"""Bakes that aim at an error: the direction count chosen from a pilot bake's estimate of its
own error (core.transport.estimate), instead of set by hand.

A bake at a Target Error first bakes a pilot at PILOT_DIRECTIONS (or at the count the scene's
last such bake chose). Where the pilot's estimated error already meets the target, the pilot is
the bake. Else the gathered light's share of the error is what more directions lower: its
estimate falls as D^-GATHER_ERROR_EXPONENT, so the count that brings it within what the direct
light's error leaves of the target is predicted from the pilot alone, and the scene is baked
once more at that count. The direct light's error does not fall with directions (it is the
footprint's and the lamps' points): where it alone exceeds the target, the gathered light is
brought to its level, and the report says so.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

# The pilot's direction count where the scene has no earlier choice: cheap beside any bake
# that needs more, and enough rotations per filter window for a usable estimate.
PILOT_DIRECTIONS = 64
# The counts the choice rounds up to (each about 1.5x the one before), the last the most it chooses.
DIRECTION_STEPS = (64, 96, 128, 192, 256, 384, 512, 768, 1024, 1536, 2048)
# The gathered light's estimated error against the direction count D falls as D^-exponent: 0.5
# for independent directions; 0.80 on a room lit only by a spot's patch (tests/core/test_estimate.py),
# 0.41-0.69 from 64 to 256 directions on the eight benchmark scenes, where the light's own change
# across the filter window is a floor the estimate keeps (benchmarks/error_calibration.py, in
# docs/benchmarks.md). The Monte Carlo rate: most scenes meet the target in one step, and those
# that fall slower say so in the report.
GATHER_ERROR_EXPONENT = 0.5
# The share of the target the estimate aims at: what the estimate does not see (the bias of
# penumbrae probed from the texel's centre, the filter's blur, emitters sampled directly) comes on top.
AIM = 0.85


@dataclass
class DirectionChoice:
    """What a bake at a target error chose, for its report.

    directions : the count the bake's light comes from
    pilot_directions : the pilot's count (the same as ``directions`` where the pilot was kept)
    pilot_estimate : the pilot's estimated error (core.transport.estimate.lighting_error), or None
    predicted : the estimated error expected at ``directions`` (the pilot's where it was kept)
    reason : why, in one sentence
    """

    target: float
    directions: int
    pilot_directions: int
    pilot_estimate: dict | None
    predicted: float | None
    reason: str

    def as_dict(self) -> dict:
        return {"target_error": self.target, "directions": self.directions,
                "pilot_directions": self.pilot_directions, "pilot_estimate": self.pilot_estimate,
                "predicted_error": None if self.predicted is None else float(f"{self.predicted:.4g}"),
                "reason": self.reason}


def choose_directions(estimate: dict | None, pilot: int, target: float, most: int = DIRECTION_STEPS[-1]
                      ) -> DirectionChoice:
    """The direction count for ``target`` (relative RMS error per texel) from a pilot at ``pilot``
    directions whose estimated error is ``estimate`` (total, lamps, gathered; None: no estimate);
    at most ``most`` directions."""
    def kept(reason, predicted=None):
        return DirectionChoice(target, pilot, pilot, estimate, predicted, reason)

    if not estimate or estimate.get("total") is None:
        return kept("the pilot has no estimate of its error (no lighting pass, or no interleaved rotations): "
                    "its directions were kept")
    total, direct, gathered = estimate["total"], estimate["lamps"] or 0.0, estimate["gathered"] or 0.0
    aim = AIM * target
    if total <= aim:
        return kept(f"the pilot's estimated error {total:.2%} is within the target {target:.2%}", total)
    note = ""
    if direct >= aim:
        # The target cannot be met by directions: the gathered light is brought to the lamps' level,
        # beyond which more directions buy little.
        if gathered <= direct:
            return kept(f"the lamps' direct light's estimated error {direct:.2%} alone exceeds the target "
                        f"{target:.2%}: more directions do not lower it (Texel Footprint Samples and the "
                        "lamps' points do)", total)
        budget = direct
        note = (f"; the lamps' direct light's estimated error {direct:.2%} alone exceeds the target "
                f"{target:.2%} (Texel Footprint Samples and the lamps' points lower it), so the gathered light "
                "was brought to its level")
    else:
        # What the direct light's error leaves of the aim, for the gathered light's.
        budget = math.sqrt(aim * aim - direct * direct)
    wanted = pilot * (gathered / budget) ** (1.0 / GATHER_ERROR_EXPONENT)
    steps = [step for step in DIRECTION_STEPS if step <= most]
    chosen = next((step for step in steps if step >= wanted), steps[-1] if steps else pilot)
    if chosen <= pilot:
        return kept(f"the pilot's estimated error {total:.2%} is near the target {target:.2%}: its directions "
                    "were kept", total)
    predicted = math.sqrt(direct * direct + (gathered * (pilot / chosen) ** GATHER_ERROR_EXPONENT) ** 2)
    limited = "" if chosen >= wanted else f" (the most this bake chooses; {wanted:.0f} were wanted)"
    return DirectionChoice(target, chosen, pilot, estimate, predicted,
                           f"the pilot at {pilot} directions estimated {total:.2%} (gathered light {gathered:.2%}); "
                           f"{chosen} directions{limited} bring it to about {predicted:.2%}{note}")
