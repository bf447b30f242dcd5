"""The transport contract: what every pass works on, and what a backend implements.

A backend (the numpy passes of :mod:`core.transport`, or the GLSL passes of
``gpu_shaders``) implements :class:`TransportBackend`. The bake hands it small typed
structures instead of a prepared scene:

- :class:`SampleSet`: where the samples are (positions, normals, ray origins);
- :class:`Shadowing`: how direct light is shadowed (exact rays, or the paper's shadow
  fractions from the table);
- :class:`GatherGeometry`: the light-independent half of a gather (table, normals,
  normalisation, atlas layout);
- :class:`GatherSource`: the light a gather looks up (radiance atlas, world, exclusions).

A gather may be restricted to a contiguous range of directions. The weights are
normalised over the whole direction set (:func:`core.transport.gather.gather_normalisation`),
so gathers over disjoint ranges that cover the set add up to the full gather: work can
be split by direction across threads, devices or machines.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from ..visibility.directions import ShadowRegions
from ..visibility.rays import RayScene, offset_ray_origins
from ..visibility.shadows import ShadowFractions, shadow_fractions


@dataclass(frozen=True)
class SampleSet:
    """The surface samples a pass evaluates.

    position : (K, 3) float64 world space
    normal : (K, 3) float64 unit shading normals
    geometric : (K, 3) float64 unit geometric normals (the side rays leave from)
    origins : (K, 3) float32 ray origins, offset off the surface along ``geometric``
    """

    position: np.ndarray
    normal: np.ndarray
    geometric: np.ndarray
    origins: np.ndarray

    @classmethod
    def on_surface(cls, position: np.ndarray, normal: np.ndarray,
                   geometric: np.ndarray | None = None) -> SampleSet:
        """Samples at ``position`` (K, 3); without ``geometric`` the shading normal is also the face's."""
        geometric = normal if geometric is None else geometric
        return cls(position, normal, geometric, offset_ray_origins(position, geometric))

    def __len__(self) -> int:
        return len(self.position)


@dataclass
class Shadowing:
    """How direct light is shadowed for one sample set.

    mode : 'exact' (one shadow ray per sample and lamp point, through ``ray_scene``) or
        'fractions' (the paper's shadow fractions, looked up from ``table``; no ray)
    area_light_samples : grid points per side an area lamp is integrated with
    region_count : number of shadow regions c_j (fractions only)

    The distant lights' fractions are computed once and shared by every sun of every
    lighting that uses this object.
    """

    mode: str
    ray_scene: RayScene
    area_light_samples: int
    table: object = None  # VisibilityTable (or a deferred one); needed for fractions
    directions: np.ndarray | None = None  # (N, 3) float64 the table's direction set
    region_count: int = 32
    _regions: ShadowRegions | None = field(default=None, repr=False)
    _distant: ShadowFractions | None = field(default=None, repr=False)

    @classmethod
    def exact(cls, ray_scene: RayScene, area_light_samples: int) -> Shadowing:
        return cls("exact", ray_scene, area_light_samples)

    def regions(self) -> ShadowRegions:
        if self._regions is None:
            self._regions = ShadowRegions(self.directions, self.region_count)
        return self._regions

    def distant_fractions(self) -> ShadowFractions:
        """The shadow fractions for lights at infinity (suns)."""
        if self._distant is None:
            self._distant = shadow_fractions(self.table, self.regions())
        return self._distant

    def local_fractions(self, light_distance: np.ndarray) -> ShadowFractions:
        """The shadow fractions for a lamp at ``light_distance`` (K,) from each sample."""
        return shadow_fractions(self.table, self.regions(), light_distance)


@dataclass(frozen=True)
class GatherGeometry:
    """What every gather over one prepared scene shares: it depends on no light.

    table : VisibilityTable (hit_object, hit_uv, hit_triangle per direction and sample)
    normals : (K, 3) float64 shading normals
    scale : (K,) float64 per-sample normalisation of the weights (sum to pi)
    layout : core.transport.gather.AtlasLayout of the radiance atlases
    threads : CPU worker threads (0: all cores); backends without threads ignore it
    """

    table: object
    normals: np.ndarray
    scale: np.ndarray
    layout: object
    threads: int = 0


@dataclass(frozen=True)
class GatherSource:
    """The light one gather looks up.

    radiance : (layout.size, C) float32 packed outgoing radiance of every object, 3
        channels per light group gathered together
    world : (N, C) or (C,) float radiance of rays that leave the scene
    exclude : (K, objects) bool or None; True where a sample must not gather an object
        (its light reaches the sample another way, e.g. a directly sampled emitter)
    """

    radiance: np.ndarray
    world: np.ndarray
    exclude: np.ndarray | None = None


def direction_chunks(count: int, parts: int) -> list[range]:
    """``parts`` contiguous ranges of nearly equal size covering ``range(count)``: the
    direction subsets whose gathers add up to the whole one."""
    parts = max(1, min(int(parts), count)) if count else 1
    bounds = np.linspace(0, count, parts + 1).round().astype(int)
    return [range(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:])]


class TransportBackend(Protocol):
    """The passes a device implements. ``name`` ('cpu' or 'gpu') goes into the report."""

    name: str

    def lamp_irradiance(self, samples: SampleSet, shadowing: Shadowing, lights, report=None
                        ) -> tuple[np.ndarray, int]:
        """(K, 3) float64 irradiance of ``lights`` (core.scene.Light) and the shadow rays traced;
        ``report(fraction)`` after each lamp."""

    def gather(self, geometry: GatherGeometry, source: GatherSource, progress=None,
               samples: np.ndarray | None = None, directions: range | None = None) -> np.ndarray:
        """E(p) = sum_i w_i(p) L(S_i[p]), (K, C) float64.

        samples : (k,) int64 or None; only these samples are needed (the others get 0)
        directions : a contiguous range of direction indices, or None for all
        """

    def accumulate_passes(self, albedo: np.ndarray, wants, groups: dict, per_group: bool) -> dict:
        """Pass name -> (K, 3) float64 from the groups' transported irradiance."""

    def dilate(self, image: np.ndarray, coverage: np.ndarray, margin: int) -> tuple[np.ndarray, np.ndarray]:
        """``image`` (H, W[, C]) extended ``margin`` texels beyond ``coverage`` (H, W) bool."""
