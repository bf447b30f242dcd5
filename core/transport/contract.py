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
    owner : (K,) int64 index of the mesh each sample lies on (in :attr:`Shadowing.mesh_names`'
        order), or None when unknown (then every lamp lights every sample, linked or not)
    footprint : (K, P, 3) float32 offsets from ``position`` of points over each sample's texel
        footprint (core.sampling.footprint), or None: each sample stands for its position;
        exact shadows are averaged over them
    footprint_corners : (K, 4, 3) float32 offsets to the corners of each texel's box, where
        exact shadows probe for an edge crossing it; None without a footprint
    terminator : (K, 3) float64 lift towards the smooth surface of smooth-shaded faces, and
    terminator_cutoff : (K,) float64 the object's cosine below which it applies
        (core.sampling.terminator); None: no sample is on a smooth face
    footprint_normals : (K, P, 3) float32 the shading normal at each footprint point, with
        which direct light is shaded there; None: every point takes ``normal``
    dense_footprint : callable (rows (r,) int64, count) -> (offsets (r, count, 3) float32,
        normals (r, count, 3) float32 or None): a denser footprint of samples ``rows``, of
        which the first P points are ``footprint``'s; None: there is none
    derived : light-independent arrays the passes derive from the samples, kept with them
        so that every relight of a preparation reuses them (keyed by the pass's own name)
    ids : (K,) int64 each sample's index in the whole bake, which seeds its randomness (the
        direct-light sampler's scramble) and indexes ``dense_footprint``; None: 0..K-1 (the
        set is the whole bake). A set of some rows of the bake (:meth:`rows`) keeps them, so
        its samples' direct light is bitwise theirs in the whole set.
    """

    position: np.ndarray
    normal: np.ndarray
    geometric: np.ndarray
    origins: np.ndarray
    owner: np.ndarray | None = None
    footprint: np.ndarray | None = None
    footprint_corners: np.ndarray | None = None
    terminator: np.ndarray | None = None
    terminator_cutoff: np.ndarray | None = None
    footprint_normals: np.ndarray | None = None
    dense_footprint: object = None
    derived: dict = field(default_factory=dict, repr=False, compare=False)
    ids: np.ndarray | None = None

    @classmethod
    def on_surface(cls, position: np.ndarray, normal: np.ndarray,
                   geometric: np.ndarray | None = None) -> SampleSet:
        """Samples at ``position`` (K, 3); without ``geometric`` the shading normal is also the face's."""
        geometric = normal if geometric is None else geometric
        return cls(position, normal, geometric, offset_ray_origins(position, geometric))

    def __len__(self) -> int:
        return len(self.position)

    def sample_ids(self) -> np.ndarray:
        """(K,) int64 each sample's index in the whole bake: :attr:`ids`, or 0..K-1 without them."""
        if self.ids is None:
            return np.arange(len(self.position), dtype=np.int64)
        return np.asarray(self.ids, np.int64)

    def rows(self, start: int, stop: int) -> SampleSet:
        """Samples [start, stop) of this set (0 <= start <= stop <= K), as a worker of a bake split
        by sample rows evaluates them: every per-sample array sliced (views), ``ids`` their
        indices in the whole bake, ``dense_footprint`` shared (it takes those indices), and
        ``derived`` empty (what a pass derives belongs to the set it was derived from)."""
        count = len(self.position)
        if not 0 <= start <= stop <= count:
            raise ValueError(f"rows [{start}, {stop}) outside the set's {count} samples")
        cut = slice(start, stop)

        def sliced(values):
            return None if values is None else values[cut]

        return SampleSet(self.position[cut], self.normal[cut], self.geometric[cut], self.origins[cut],
                         sliced(self.owner), sliced(self.footprint), sliced(self.footprint_corners),
                         sliced(self.terminator), sliced(self.terminator_cutoff), sliced(self.footprint_normals),
                         self.dense_footprint, ids=self.sample_ids()[cut])


@dataclass
class Shadowing:
    """How direct light is shadowed for one sample set.

    mode : 'exact' (one shadow ray per sample and lamp point, through ``ray_scene``) or
        'fractions' (the paper's shadow fractions, looked up from ``table``; no ray)
    area_light_samples : its square is the sampler points a lamp with an extent is integrated with
    region_count : number of shadow regions c_j (fractions only)
    mesh_names : the names of ``ray_scene``'s geometries, in order (light and shadow linking)
    casts_shadow : (meshes,) bool or None; False where a mesh's shadow visibility is off
    seed : the bake seed, which scrambles the direct-light sampler's points
    footprint_samples : points a texel's footprint holds (the samples' footprint), for estimates

    The distant lights' fractions are computed once and shared by every sun of every
    lighting that uses this object; so is each lamp's scene of shadow blockers.
    """

    mode: str
    ray_scene: RayScene
    area_light_samples: int
    table: object = None  # VisibilityTable (or a deferred one); needed for fractions
    directions: np.ndarray | None = None  # (N, 3) float64 the table's direction set
    region_count: int = 32
    mesh_names: tuple = ()
    casts_shadow: np.ndarray | None = None
    seed: int = 0
    footprint_samples: int = 1
    rotations: np.ndarray | None = None  # (G, 3, 3) the table's interleaved rotations, or None
    group: np.ndarray | None = None  # (K,) each sample's rotation
    _regions: ShadowRegions | None = field(default=None, repr=False)
    _distant: ShadowFractions | None = field(default=None, repr=False)
    _blockers: dict = field(default_factory=dict, repr=False)

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
            self._distant = shadow_fractions(self.table, self.regions(), None, self.rotations, self.group)
        return self._distant

    def local_fractions(self, light_distance: np.ndarray) -> ShadowFractions:
        """The shadow fractions for a lamp at ``light_distance`` (K,) from each sample."""
        return shadow_fractions(self.table, self.regions(), light_distance, self.rotations, self.group)

    def blocker_scene(self, light) -> RayScene | None:
        """The scene ``light``'s exact shadow rays are traced against: every mesh that casts
        shadows and, with shadow linking, is one of its blockers; None: nothing shadows it."""
        if not light.casts_shadows:
            return None
        count = len(self.mesh_names)
        casting = np.ones(count, bool) if self.casts_shadow is None else np.asarray(self.casts_shadow, bool)
        if light.blockers is not None:
            casting = casting & np.isin(np.array(self.mesh_names, object), list(light.blockers))
        if not count or casting.all():
            return self.ray_scene
        key = tuple(np.nonzero(casting)[0])
        if key not in self._blockers:
            self._blockers[key] = self.ray_scene.subset(key)
        return self._blockers[key]

    def receivers(self, light, samples: SampleSet) -> np.ndarray | None:
        """(K,) bool: the samples ``light`` lights (light linking); None: all of them."""
        if light.receivers is None or samples.owner is None:
            return None
        lit = np.isin(np.array(self.mesh_names, object), list(light.receivers))
        return lit[samples.owner]


@dataclass(frozen=True)
class GatherGeometry:
    """What every gather over one prepared scene shares: it depends on no light.

    table : VisibilityTable (hit_object, hit_uv_code per direction and sample, vertex_cells)
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

    def lamp_irradiance(self, samples: SampleSet, shadowing: Shadowing, lights, report=None,
                        spread: list | None = None) -> tuple[np.ndarray, int]:
        """(K, 3) float64 irradiance of ``lights`` (core.scene.Light) and the shadow rays traced;
        ``report(fraction)`` after each lamp; ``spread``: a list, to which the light's standard
        error (K, 3) float64 is appended (core.transport.direct.lamp_irradiance)."""

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
