"""Light groups: the lamps, world light and emitting objects whose light is carried
together (core.pipeline.transport carries them through a backend).

Transport is linear in the emitted light, so each light group (a set of lamps, the
world, emitting objects) can be carried separately and the groups sum to the whole.
Separate groups cost little more than one: a gather's cost is the table walk and the
bilinear index arithmetic, not the width of what it looks up, so G groups are
gathered together as one radiance atlas with 3G channels.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# Groups gathered together at most: the per-sample accumulators hold 3 channels per
# group in float64 per worker thread (403k samples x 48 channels ~ 155 MB each).
MAX_GROUPS_PER_GATHER = 16


@dataclass
class LightGroup:
    """Lights, world and emitting objects whose light is transported together.

    world : (N, 3) float64 world radiance per direction
    emitting : (objects,) bool, whose emission belongs to this group
    """

    name: str
    lights: list
    world: np.ndarray
    emitting: np.ndarray


@dataclass
class Transported:
    """Per-sample irradiance of one group: direct (lamps, emitters, world) and gathered bounces,
    and the squared standard errors the bake estimated (core.transport.estimate), (K, 3) float64,
    NaN where it has no estimate, None where it has none at all (read back from a cache): of the
    lamps' direct light (``direct_variance``), and of all light that came through the table
    (``gathered_variance``: the world's and emitters' gather, and the bounces)."""

    direct: np.ndarray  # (K, 3) float64
    gathered: np.ndarray  # (K, 3) float64
    shadow_rays: int = 0
    emitter_rays: int = 0
    emitters_sampled: tuple = ()
    direct_variance: np.ndarray | None = None
    gathered_variance: np.ndarray | None = None


def light_groups(meshes, emission: np.ndarray, sample_offset: np.ndarray, lights, world: np.ndarray,
                 world_group: str, split: bool) -> list[LightGroup]:
    """The groups of one lighting: one with everything, or one per light group.

    meshes : the bake's core.scene.Mesh objects; emission : (K, 3) per-sample emitted
    radiance; sample_offset : (objects + 1,) first sample of each object.

    A lamp's group is its ``group`` or its own name; the world's is ``world_group`` or
    "world"; an emitting object's is its ``light_group`` or its own name.
    """
    objects = len(meshes)
    emits = np.array([bool(np.any(emission[a:b] > 0)) for a, b in zip(sample_offset[:-1], sample_offset[1:])],
                     bool)
    if not split:
        return [LightGroup("all", list(lights), world, emits)]
    groups: dict[str, LightGroup] = {}

    def group(name):
        if name not in groups:
            groups[name] = LightGroup(name, [], np.zeros_like(world), np.zeros(objects, bool))
        return groups[name]

    for light in lights:
        group(light.group or light.name).lights.append(light)
    if np.any(world > 0):
        group(world_group or "world").world = world
    for index in np.nonzero(emits)[0]:
        mesh = meshes[index]
        group(mesh.light_group or mesh.name).emitting[index] = True
    return list(groups.values())


def light_key_parts(light) -> list:
    """What a lamp contributes to a lighting key: every value but its names."""
    parts = []
    for name, value in sorted(vars(light).items()):
        if name in ("name", "group"):
            continue
        parts.append(name)
        parts.append(np.asarray(value, np.float64) if isinstance(value, np.ndarray) else value)
    return parts


