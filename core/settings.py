"""Every setting of a bake, its choices, defaults and limits, validated in one place.

The command line, the Blender properties and the panel take their choices, defaults,
ranges and help text from here (:data:`SETTINGS`), and
:func:`BakeSettings.validate` is the one check of a complete set of values.
"""
from __future__ import annotations

from dataclasses import dataclass


LIGHTING_PASSES = ("lighting", "direct", "indirect", "irradiance")


PASSES = ("lighting", "direct", "indirect", "irradiance", "ao")


SHADOW_MODES = ("fractions", "exact")


SAMPLE_MODES = ("atlas", "vertex")


VERTEX_LOOKUPS = ("interpolate", "nearest")


@dataclass
class BakeSettings:
    """Everything that changes the result of a bake.

    directions : size of the global direction set D
    bounces : diffuse bounces after the first (Cycles' ``diffuse_bounces``)
    shadows : 'fractions' (the paper: no ray at lighting time) or 'exact'
    shadow_regions : number of regions c_j for the fractions
    rotate : randomly rotate D (seeded) to turn ray effects into noise
    passes : output passes, a subset of PASSES
    margin : gutter width in texels that results are dilated into
    area_light_samples : grid points per side used to integrate an area light
    emitter_samples : points per emissive object for direct sampling of small emitters
    threads : worker threads for ray tracing (0: all cores)
    light_groups : also write every lighting pass per light group, so lights can be
        re-mixed without another bake (the groups sum to the combined pass)
    vertex_lookup : how a ray landing on a vertex-mode object reads its light:
        'interpolate' (barycentric mix of the triangle's three samples) or 'nearest'
        (the paper's nearest vertex)
    chunk_rays : rays traced per batch; bounds the memory of the tracing stage
    """

    directions: int = 128
    bounces: int = 2
    shadows: str = "exact"
    shadow_regions: int = 32
    rotate: bool = False
    seed: int = 0
    passes: tuple[str, ...] = ("lighting",)
    margin: int = 4
    area_light_samples: int = 8
    emitter_samples: int = 16
    threads: int = 0
    chunk_rays: int = 1 << 20
    light_groups: bool = False
    vertex_lookup: str = "interpolate"

    def validate(self) -> None:
        """Raise ValueError with a one-line reason for settings that cannot work."""
        if self.directions < 1:
            raise ValueError(f"directions must be >= 1, got {self.directions}")
        if self.bounces < 0:
            raise ValueError(f"bounces must be >= 0, got {self.bounces}")
        if self.shadows not in SHADOW_MODES:
            raise ValueError(f"shadows must be one of {', '.join(SHADOW_MODES)}, got {self.shadows!r}")
        if self.shadow_regions < 1:
            raise ValueError(f"shadow regions must be >= 1, got {self.shadow_regions}")
        unknown = [p for p in self.passes if p not in PASSES]
        if unknown or not self.passes:
            raise ValueError(f"passes: choose at least one of {', '.join(PASSES)}"
                             + (f" (unknown: {', '.join(unknown)})" if unknown else ""))
        if self.margin < 0:
            raise ValueError(f"margin must be >= 0, got {self.margin}")
        if self.area_light_samples < 1:
            raise ValueError("area light samples must be >= 1")
        if self.emitter_samples < 1:
            raise ValueError("emitter samples must be >= 1")
        if self.vertex_lookup not in VERTEX_LOOKUPS:
            raise ValueError(f"vertex lookup must be one of {', '.join(VERTEX_LOOKUPS)}, got {self.vertex_lookup!r}")
