"""The virtual gonioreflectometer (the paper's section 7.1): a periodic tile lit by a sun from
each light direction and seen from each view direction, its BRDF the period's mean outgoing
radiance over the incident irradiance.

Units: a sun of irradiance 1 W/m^2 on a plane facing it, so the macro surface receives
cos(theta_l); then f(l, v) = L_mean(v) / cos(theta_l), 1/sr.

The steps, each the same for every light direction (the Method of Dependent Tests):
- **Tables.** For every sample (core.appearance.tile) and direction d_i of a global set
  above its horizon, the face the ray meets on the periodic surface (core.appearance.periodic),
  traced once.
- **Direct light.** Periodic shadow rays towards the light from four probes per face,
  averaged into the samples (direct_irradiance): E_0(s) ~ vis * n.l.
- **Bounces.** The radiance each sample sends towards every -d_i, then the radiance arriving
  at every sample from d_i is a lookup of the hit face's corners. A Lambert-only tile sends
  the same radiance everywhere, so its bounce is one gather per sample (gather_diffuse);
  a glossy one needs the per-direction transport (glossy_outgoing), the paper's own.
- **Views.** Masking is exact: a view is a grid of parallel rays from above along -v over
  one period's footprint, each traced on the periodic surface to the first face it meets
  (the same rays an orthographic camera averaging one period sends). What the hit point
  sends towards v, interpolated from its face's corners, averaged over the rays, is
  L_mean(v). A ray that passes through the surface sees nothing (black, as the sky below).
- **Transparency.** The share of a light's rays from above along -l that pass through the
  surface without meeting a face: the BSDF's straight-through part.

The micro-BRDF is the mixture (1 - specular) * albedo / pi + specular * lobe, with the lobe
GGX (from a roughness) or the paper's Phong (core.kernels.appearance_kernels.lobe): its
directional albedo is at most 1 by construction. Faces are one-sided (their backs are black)
unless translucent: a face of transmission t is a thin sheet that passes the share t of its
diffuse light to its other side, whose samples are its twins (core.appearance.tile), so
fibres let light through diffusely and lights and views may lie on either side (the BSDF
over the whole sphere).
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from .. import kernels
from ..errors import AppearanceRefused
from ..transport.contract import direction_chunks
from ..visibility.directions import direction_set
from ..visibility.rays import offset_ray_origins
from .periodic import ESCAPED_DOWN, ESCAPED_UP, HIT, PeriodicScene
from .tile import Tile, TileSamples, tile_samples

MIN_DIRECTIONS = 8
MAX_DIRECTIONS = 4096
# Light directions lit together: the glossy transport holds (S, N, batch, 3) float32 twice.
GLOSSY_BATCH_BYTES = 256 * 2 ** 20
DIFFUSE_BATCH = 64


def require_kernels():
    """The compiled appearance kernels; refuses with the reason where numba cannot load."""
    module = kernels.appearance()
    if module is None:
        raise AppearanceRefused("BRDF simulation needs VisiBake's compiled kernels, which cannot load here: "
                                f"{kernels.status().reason}")
    return module


@dataclass
class GonioSettings:
    """directions : N of the global set over the sphere; bounces : K inter-reflections after
    the direct light; resolution : samples across the period (core.appearance.tile);
    view_rays : rays across the period per view (view_rays^2 in all); seed : the rotation of
    the direction set (and the view grids' offsets)."""

    directions: int = 128
    bounces: int = 2
    resolution: int = 64
    view_rays: int = 128
    seed: int = 0
    threads: int = 0

    def check(self) -> None:
        if not MIN_DIRECTIONS <= self.directions <= MAX_DIRECTIONS:
            raise AppearanceRefused(f"directions must be between {MIN_DIRECTIONS} and {MAX_DIRECTIONS}, got "
                                    f"{self.directions}")
        if not 0 <= self.bounces <= 64:
            raise AppearanceRefused(f"bounces must be between 0 and 64, got {self.bounces}")
        if not 1 <= self.resolution <= 2048:
            raise AppearanceRefused(f"the resolution must be between 1 and 2048, got {self.resolution}")
        if not 4 <= self.view_rays <= 4096:
            raise AppearanceRefused(f"view rays must be between 4 and 4096 across the period, got {self.view_rays}")


@dataclass
class VisibilityTables:
    """The tile's precomputed visibility (see core.kernels.appearance_kernels for the layout).

    directions : (N, 3) float64 unit; hit_corner : (S, N, 3) int32; hit_weight : (S, N, 3)
    float32; cos_weight : (S, N) float32
    """

    directions: np.ndarray
    hit_corner: np.ndarray
    hit_weight: np.ndarray
    cos_weight: np.ndarray

    @property
    def nbytes(self) -> int:
        return self.hit_corner.nbytes + self.hit_weight.nbytes + self.cos_weight.nbytes


@dataclass
class ViewWeights:
    """What each view sees: weights (V, S) float32, the share of the view's rays that land on
    each sample (barycentric), so that L_mean(v) = weights[v] @ L(samples, v); back_share
    (V,) the share that met a face from behind."""

    weights: np.ndarray
    back_share: np.ndarray


@dataclass
class BRDFSamples:
    """The simulated BSDF of a tile.

    light : (L, 3) float64 unit, towards the light; view : (V, 3) float64 unit, towards the
        viewer (tile frame, z up)
    values : (L, V, 3) float64 BSDF, 1/sr: reflection where the light and the view lie on
        one side of the tile, transmission where they lie on opposite sides (0 for a light
        in the tile's plane)
    transparency : (L,) float64 share of each light's rays that passes straight through
    stats : what it took (seconds per stage, counts) for the report
    warnings : what was noticed
    """

    light: np.ndarray
    view: np.ndarray
    values: np.ndarray
    transparency: np.ndarray
    stats: dict = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)


def hemisphere_directions(count: int) -> np.ndarray:
    """``count`` (>= 1) unit directions spread evenly over the upper hemisphere: a Fibonacci
    spiral, equal-area rings in z. Returns (count, 3) float64."""
    index = np.arange(count) + 0.5
    z = 1.0 - index / count
    radius = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    angle = index * np.pi * (3.0 - np.sqrt(5.0))
    return np.column_stack([radius * np.cos(angle), radius * np.sin(angle), z])


def sphere_directions(count: int) -> np.ndarray:
    """``count`` (>= 1) unit directions spread evenly over the whole sphere (a Fibonacci
    spiral, equal-area rings in z from +1 to -1), for BSDFs: below the horizon are lights
    shining on the tile's underside and views of what it lets through. Returns (count, 3)
    float64."""
    index = np.arange(count) + 0.5
    z = 1.0 - 2.0 * index / count
    radius = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    angle = index * np.pi * (3.0 - np.sqrt(5.0))
    return np.column_stack([radius * np.cos(angle), radius * np.sin(angle), z])


def seen_corners(samples: TileSamples, faces: np.ndarray, direction: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The samples that shade the side of ``faces`` (n,) int32 a ray along ``direction``
    ((n, 3) or (3,) float64) arrives at: (corners (n, 3) int32, from_behind (n,) bool). A
    translucent face's back has samples of its own; an opaque face's back answers with its
    front's (the caller decides whether a back counts as black)."""
    from_behind = np.einsum("nx,nx->n", samples.face_normal[faces], np.broadcast_to(direction, (len(faces), 3))) > 0
    corners = samples.triangles[faces]
    back = samples.back_triangles[faces]
    own_back = from_behind & (back[:, 0] >= 0)
    corners[own_back] = back[own_back]
    return corners, from_behind & ~own_back


def build_tables(samples: TileSamples, scene: PeriodicScene, directions: np.ndarray) -> VisibilityTables:
    """Trace every sample along every direction above its horizon on the periodic surface."""
    count = len(samples)
    n = len(directions)
    cosines = samples.normal @ directions.T
    above = cosines > 0
    rows, columns = np.nonzero(above)
    origins = offset_ray_origins(samples.position[rows], samples.normal[rows]).astype(np.float64)
    hits = scene.trace(origins, directions[columns])
    hit_corner = np.full((count, n, 3), -1, np.int32)
    hit_weight = np.zeros((count, n, 3), np.float32)
    met = hits.fate == HIT
    hit_corner[rows[met], columns[met]] = seen_corners(samples, hits.triangle[met], directions[columns[met]])[0]
    hit_weight[rows[met], columns[met]] = hits.barycentric[met]
    # A finite set's cosine weights sum to pi over an open hemisphere only on average: scaled
    # per sample so that they do, a white groove cannot reflect more than it receives.
    cos_weight = np.where(above, cosines, 0.0)
    total = cos_weight.sum(axis=1, keepdims=True)
    cos_weight = (cos_weight * np.where(total > 0, np.pi / np.maximum(total, 1e-300), 0.0)).astype(np.float32)
    return VisibilityTables(directions, hit_corner, hit_weight, cos_weight)


def _outside(scene: PeriodicScene, towards: np.ndarray) -> float:
    """The height just outside the tile's slab on the side ``towards`` (3,) points to: where
    parallel rays coming from that side start."""
    margin = 0.01 * float(scene.period.max()) + 1e-6
    return scene.z_range[1] + margin if towards[2] > 0 else scene.z_range[0] - margin


def view_weights(samples: TileSamples, scene: PeriodicScene, views: np.ndarray, rays: int,
                 seed: int = 0) -> ViewWeights:
    """Trace each view's grid of parallel rays and spread each hit over its face's corners.

    views : (V, 3) float64 unit, above or below the horizon (a view from below looks up at
    the tile's underside, and through it). The rays pass through rays x rays cells
    of the period, each at a random point of its cell (from ``seed``): a regular grid aliases
    with a tile's regular structure (measured: 0.3% too much weight on a V-groove's lit
    samples), a jittered one is unbiased.
    """
    count = len(samples)
    weights = np.zeros((len(views), count), np.float32)
    back = np.zeros(len(views))
    rng = np.random.default_rng(seed)
    cells = np.arange(rays)
    gx, gy = np.meshgrid(cells, cells, indexing="ij")
    for index, v in enumerate(views):
        jitter = rng.random((2, rays * rays))
        points = np.column_stack([scene.origin[0] + (gx.ravel() + jitter[0]) / rays * scene.period[0],
                                  scene.origin[1] + (gy.ravel() + jitter[1]) / rays * scene.period[1],
                                  np.full(rays * rays, _outside(scene, v))])
        hits = scene.trace(points, np.tile(-v, (len(points), 1)))
        met = hits.fate == HIT
        corners, black = seen_corners(samples, hits.triangle[met], -v)
        back[index] = np.count_nonzero(black) / len(points)
        corners = corners[~black]
        shares = hits.barycentric[met][~black] / len(points)
        np.add.at(weights[index], corners.ravel(), shares.ravel())
    return ViewWeights(weights, back)


# Where each face is probed for the sun: the centroids of its four midpoint sub-triangles, as
# barycentric weights of its corners (rows).
FACE_PROBES = np.array([[2 / 3, 1 / 6, 1 / 6], [1 / 6, 2 / 3, 1 / 6], [1 / 6, 1 / 6, 2 / 3], [1 / 3, 1 / 3, 1 / 3]])


def direct_irradiance(samples: TileSamples, scene: PeriodicScene, light: np.ndarray) -> np.ndarray:
    """(S,) float64: each sample's irradiance from a sun of unit irradiance along ``light``
    (unit), as the average of the shadowed n.l over the faces around it, weighted by the
    sample's hat function (its barycentric weight).

    A sample's own shadow test would put a shadow's edge at the samples' spacing: the
    interpolation between a lit and a shadowed sample spreads the light half a spacing
    past the edge, a bias of a few percent under a grazing sun (measured on a V-groove: 3%
    at 75 degrees). The hat-weighted averages of the probes integrate to the exact lit area
    over any face the samples interpolate across.
    """
    # The faces' fronts, and the backs of translucent ones (facing the other way).
    translucent = samples.back_triangles[:, 0] >= 0
    faces = np.concatenate([samples.triangles, samples.back_triangles[translucent]])
    face_normal = np.concatenate([samples.face_normal, -samples.face_normal[translucent]])
    face_area = np.concatenate([samples.face_area, samples.face_area[translucent]])
    corners_normal = samples.normal[faces]  # (F, 3, 3)
    normal = np.einsum("pc,fcx->fpx", FACE_PROBES, corners_normal)
    normal /= np.maximum(np.linalg.norm(normal, axis=2, keepdims=True), 1e-300)
    position = np.einsum("pc,fcx->fpx", FACE_PROBES, samples.position[faces])
    cosine = (normal @ light).reshape(-1)
    facing = np.nonzero(cosine > 0)[0]
    shaded = np.zeros(len(cosine))
    if len(facing):
        geometric = np.repeat(face_normal, len(FACE_PROBES), axis=0)[facing]
        origins = offset_ray_origins(position.reshape(-1, 3)[facing], geometric).astype(np.float64)
        hits = scene.trace(origins, np.tile(light, (len(facing), 1)))
        open_sky = hits.fate == (ESCAPED_UP if light[2] > 0 else ESCAPED_DOWN)
        shaded[facing[open_sky]] = cosine[facing[open_sky]]
    weight = (FACE_PROBES[None] * face_area[:, None, None]).reshape(-1, 3)  # (F * P, 3)
    corner = np.repeat(faces, len(FACE_PROBES), axis=0)
    total = np.zeros(len(samples))
    norm = np.zeros(len(samples))
    np.add.at(total, corner.ravel(), (weight * shaded[:, None]).ravel())
    np.add.at(norm, corner.ravel(), weight.ravel())
    return np.where(norm > 0, total / np.maximum(norm, 1e-300), 0.0)


def transparency(scene: PeriodicScene, light: np.ndarray, rays: int) -> float:
    """The share of parallel rays along -``light`` from the light's side of the tile (above or
    below) that pass through it to the other side."""
    u = (np.arange(rays) + 0.5) / rays
    gx, gy = np.meshgrid(u, u, indexing="ij")
    points = np.column_stack([scene.origin[0] + gx.ravel() * scene.period[0],
                              scene.origin[1] + gy.ravel() * scene.period[1], np.full(gx.size, _outside(scene, light))])
    hits = scene.trace(points, np.tile(-light, (len(points), 1)))
    through = ESCAPED_DOWN if light[2] > 0 else ESCAPED_UP
    return float(np.count_nonzero(hits.fate == through) / len(points))


def _unit(vectors, name: str) -> np.ndarray:
    vectors = np.asarray(vectors, np.float64).reshape(-1, 3)
    length = np.linalg.norm(vectors, axis=1, keepdims=True)
    if len(vectors) == 0 or not np.all(np.isfinite(vectors)) or np.any(length == 0):
        raise AppearanceRefused(f"the {name} directions must be finite, non-zero vectors (got {len(vectors)})")
    return vectors / length


@dataclass
class _Prepared:
    """What every light direction shares: the samples, the periodic scene, the tables."""

    samples: TileSamples
    scene: PeriodicScene
    directions: np.ndarray
    tables: VisibilityTables
    diffuse_albedo: np.ndarray  # (S, 3) float32 (1 - specular) (1 - transmission) albedo / pi, reflected
    transmit_albedo: np.ndarray  # (S, 3) float32 (1 - specular) transmission albedo / pi, to the twin's side
    stats: dict
    warnings: list

    def sent_diffuse(self, irradiance: np.ndarray, rows: np.ndarray | None = None) -> np.ndarray:
        """(R, B, 3) float64: the diffuse radiance the samples ``rows`` (R,) int64 (default:
        all) send, from the irradiance (S, B, 3) on their own side and, through a
        translucent face, on their twin's."""
        rows = np.arange(len(self.samples)) if rows is None else rows
        sent = self.diffuse_albedo[rows][:, None, :] * irradiance[rows]
        twin = self.samples.twin[rows]
        has = np.nonzero(twin >= 0)[0]
        if len(has):
            sent[has] += self.transmit_albedo[rows[has]][:, None, :] * irradiance[twin[has]]
        return sent


def _prepare(tile: Tile, settings: GonioSettings, report) -> _Prepared:
    import time
    started = time.perf_counter()
    stats: dict = {}
    report("samples", 0.0)
    samples = tile_samples(tile, settings.resolution)
    scene = PeriodicScene(samples.position, samples.triangles, tile.period, tile.origin, settings.threads)
    directions = direction_set(settings.directions, rotate=True, seed=settings.seed)
    stats["samples"] = len(samples)
    stats["faces"] = len(samples.triangles)
    stats["samples_s"] = round(time.perf_counter() - started, 3)
    mark = time.perf_counter()
    report("visibility tables", 0.05)
    tables = build_tables(samples, scene, directions)
    stats["tables_s"] = round(time.perf_counter() - mark, 3)
    stats["table_mib"] = round(tables.nbytes / 2 ** 20, 1)
    diffuse = (1.0 - samples.specular)[:, None] * samples.albedo / np.pi
    transmission = samples.transmission[:, None]
    return _Prepared(samples, scene, directions, tables, ((1.0 - transmission) * diffuse).astype(np.float32),
                     (transmission * diffuse).astype(np.float32), stats, list(tile.warnings))


@dataclass
class _LitBatch:
    """The light of a batch of b light directions, ready to be viewed.

    first : index of the batch's first light; lights : (b, 3)
    direct : (S, b) float64 the direct irradiance (sun of unit irradiance)
    irradiance : (S, b, 3) float64 direct plus the bounces' irradiance
    incoming : (S, N, b, 3) float32 the bounces' radiance arriving from each direction (glossy
        tiles only; None for Lambert ones, whose outgoing light is view-independent)
    """

    first: int
    lights: np.ndarray
    direct: np.ndarray
    irradiance: np.ndarray
    incoming: np.ndarray | None


def light_batch(tile: Tile, samples: int, directions: int) -> int:
    """The lights simulated together: all a batch's lights share each bounce's table walk, and
    a glossy batch holds (samples, directions, lights) radiances in memory."""
    if not tile.glossy:
        return DIFFUSE_BATCH
    return max(1, min(DIFFUSE_BATCH, GLOSSY_BATCH_BYTES // max(1, samples * directions * 3 * 4 * 2)))


def part_lights(light_count: int, batch: int, part: tuple[int, int] | None) -> range:
    """The lights of part ``part`` = (index, count) of a run split into ``count`` parts: whole
    batches (so each is simulated as in the whole run, to the same bits), contiguous."""
    if part is None:
        return range(light_count)
    index, count = part
    chunks = direction_chunks(-(-light_count // batch), count)
    if index >= len(chunks):  # more parts than batches: this one has none
        return range(light_count, light_count)
    batches = chunks[index]
    return range(min(batches.start * batch, light_count), min(batches.stop * batch, light_count))


def _light_batches(tile: Tile, prepared: _Prepared, lights: np.ndarray, settings: GonioSettings, module, times: dict,
                   only: range | None = None):
    """Yield a _LitBatch per batch of light directions: direct light, then the bounces (only
    the batches starting in ``only``, if given)."""
    import time
    samples, tables, directions = prepared.samples, prepared.tables, prepared.directions
    glossy = tile.glossy
    n = len(directions)
    count = len(samples)
    batch = light_batch(tile, count, n)
    threads = settings.threads
    for first in range(0, len(lights), batch):
        if only is not None and first not in only:
            continue
        chunk = lights[first:first + batch]
        b = len(chunk)
        mark = time.perf_counter()
        direct = np.stack([direct_irradiance(samples, prepared.scene, light) for light in chunk], axis=1)  # (S, b)
        times["direct_s"] = times.get("direct_s", 0.0) + time.perf_counter() - mark
        mark = time.perf_counter()
        irradiance = np.repeat(direct[:, :, None], 3, axis=2)
        incoming_total = None
        if glossy:
            incoming_total = np.zeros((count, n, b, 3), np.float32)
            sent_glossy = np.zeros((count, n, b))
            for k, light in enumerate(chunk):
                lobe = np.zeros(count * n)
                module.lobe_many(np.repeat(samples.normal, n, axis=0), np.repeat(samples.specular, n),
                                 np.repeat(samples.roughness, n), tile.phong_exponent,
                                 np.tile(light, (count * n, 1)), np.tile(-directions, (count, 1)), lobe)
                sent_glossy[:, :, k] = lobe.reshape(count, n) * direct[:, k:k + 1]
            outgoing = (prepared.sent_diffuse(irradiance)[:, None] + sent_glossy[..., None]).astype(np.float32)
            arriving = np.empty_like(outgoing)
            for bounce in range(settings.bounces):
                kernels.run(module.incoming_radiance, threads, outgoing, tables.hit_corner, tables.hit_weight, arriving)
                incoming_total += arriving
                reached = np.einsum("sn,snbc->sbc", tables.cos_weight, arriving, dtype=np.float64)
                irradiance += reached
                if bounce + 1 < settings.bounces:
                    diffuse = prepared.sent_diffuse(reached).astype(np.float32)
                    kernels.run(module.glossy_outgoing, threads, arriving, directions, samples.normal,
                                samples.specular, samples.roughness, tile.phong_exponent, tables.cos_weight, diffuse,
                                outgoing)
        else:
            sent = prepared.sent_diffuse(irradiance).astype(np.float32)
            reached = np.empty((count, b, 3))
            for _ in range(settings.bounces):
                kernels.run(module.gather_diffuse, threads, sent, tables.hit_corner, tables.hit_weight,
                            tables.cos_weight, reached)
                irradiance += reached
                sent = prepared.sent_diffuse(reached).astype(np.float32)
        times["bounces_s"] = times.get("bounces_s", 0.0) + time.perf_counter() - mark
        yield _LitBatch(first, chunk, direct, irradiance, incoming_total)


def _outgoing_towards(tile: Tile, prepared: _Prepared, lit: _LitBatch, view: np.ndarray, rows: np.ndarray,
                      module, threads: int) -> np.ndarray:
    """(R, b, 3) float64: the radiance the samples ``rows`` (R,) int64 send towards ``view``
    (unit) under each light of the batch: diffuse, the glossy lobe over the bounces' light,
    and the glossy lobe over the sun's."""
    samples = prepared.samples
    out = prepared.sent_diffuse(lit.irradiance, rows)
    if lit.incoming is None:
        return out
    towards = np.empty((len(rows), len(lit.lights), 3))
    kernels.run(module.glossy_towards, threads, lit.incoming, prepared.directions, samples.normal, samples.specular,
                samples.roughness, tile.phong_exponent, prepared.tables.cos_weight, rows, view, towards)
    out += towards
    lobe = np.empty(len(rows))
    for k, light in enumerate(lit.lights):
        module.lobe_many(samples.normal[rows], samples.specular[rows], samples.roughness[rows], tile.phong_exponent,
                         np.tile(light, (len(rows), 1)), np.tile(view, (len(rows), 1)), lobe)
        out[:, k, :] += (lobe * lit.direct[rows, k])[:, None]
    return out


# Views closer to the tile's plane than this (|z|) are refused: their parallel rays would
# cross thousands of periods before they meet the surface or leave its slab.
MIN_VIEW_Z = 1e-3


def _start(settings: GonioSettings | None, lights, views, sphere: bool = True):
    settings = settings or GonioSettings()
    settings.check()
    module = require_kernels()
    lights = _unit(lights, "light")
    views = _unit(views, "view")
    if not sphere and np.any(views[:, 2] <= 0):
        raise AppearanceRefused("view directions must lie above the tile (z > 0)")
    if np.any(np.abs(views[:, 2]) < MIN_VIEW_Z):
        raise AppearanceRefused(f"view directions must not lie in the tile's plane (|z| >= {MIN_VIEW_Z})")
    return settings, module, lights, views


def simulate_brdf(tile: Tile, lights, views, settings: GonioSettings | None = None,
                  progress: Callable[[str, float], None] | None = None, part: tuple[int, int] | None = None
                  ) -> BRDFSamples:
    """The tile's BRDF at every (light, view) pair (see the module's docstring).

    lights, views : (L, 3), (V, 3) directions (normalised here), z up, anywhere on the sphere
        but views not in the tile's plane: a light below the horizon shines on the tile's
        underside, a view below it sees the underside and what the tile lets through (its
        BSDF's transmission; with the light above, sampled with sphere_directions).
    ``progress(stage, fraction)`` is called between steps and may raise core.errors.Cancelled.
    part : (index, count), or None: only part ``index`` of the run split in ``count`` parts by
        light batches (:func:`part_lights`); its samples hold those lights alone, and
        :func:`join_brdf_parts` joins the parts into the whole run's samples, bit for bit.
    """
    import time
    settings, module, lights, views = _start(settings, lights, views)
    started = time.perf_counter()

    def report(stage: str, fraction: float) -> None:
        if progress is not None:
            progress(stage, fraction)

    prepared = _prepare(tile, settings, report)
    stats, warnings, samples = prepared.stats, prepared.warnings, prepared.samples
    mark = time.perf_counter()
    report("views", 0.2)
    seen = view_weights(samples, prepared.scene, views, settings.view_rays, settings.seed)
    stats["views_s"] = round(time.perf_counter() - mark, 3)
    if np.max(seen.back_share, initial=0.0) > 0.01:
        warnings.append(f"up to {100 * seen.back_share.max():.1f}% of a view sees the backs of faces, which are "
                        "black here: check that the tile's normals point outwards")
    values = np.zeros((len(lights), len(views), 3))
    mine = part_lights(len(lights), light_batch(tile, len(samples), len(prepared.directions)), part)
    through = np.zeros(len(lights))
    through[mine] = [transparency(prepared.scene, light, settings.view_rays) for light in lights[mine]]
    times: dict = {"gather_views_s": 0.0}
    for lit in _light_batches(tile, prepared, lights, settings, module, times, mine):
        mark = time.perf_counter()
        b = len(lit.lights)
        if lit.incoming is None:
            # Lambert: the outgoing light is the same towards every view, one product for all pairs.
            diffuse_out = prepared.sent_diffuse(lit.irradiance)
            values[lit.first:lit.first + b] += np.einsum("vs,sbc->bvc", seen.weights, diffuse_out)
        else:
            for index, view in enumerate(views):
                rows = np.nonzero(seen.weights[index] > 0)[0].astype(np.int64)
                towards = _outgoing_towards(tile, prepared, lit, view, rows, module, settings.threads)
                values[lit.first:lit.first + b, index] += np.einsum("r,rbc->bc", seen.weights[index, rows], towards)
        times["gather_views_s"] += time.perf_counter() - mark
        report("lights", 0.25 + 0.75 * min(1.0, (lit.first + b - mine.start) / max(len(mine), 1)))

    # The macro surface receives |cos theta_l| from a sun of unit irradiance on either side.
    cosine = np.abs(lights[:, 2])
    lit = cosine > 1e-9
    values[lit] /= cosine[lit, None, None]
    values[~lit] = 0.0
    if not np.all(np.isfinite(values)):
        raise RuntimeError("the BRDF simulation produced non-finite values (a bug)")
    stats.update({key: round(value, 3) for key, value in times.items()})
    stats["total_s"] = round(time.perf_counter() - started, 3)
    stats["glossy"] = tile.glossy
    if part is not None:
        stats["part"] = [int(part[0]), int(part[1])]
        return BRDFSamples(lights[mine], views, values[mine], through[mine], stats, warnings)
    return BRDFSamples(lights, views, values, through, stats, warnings)


def join_brdf_parts(parts: list[BRDFSamples]) -> BRDFSamples:
    """The samples of a run from its parts (:func:`simulate_brdf` with ``part``), in part order:
    bit for bit the whole run's. The stats are the first part's (the others' add theirs under
    ``parts``), the warnings each said once."""
    first = parts[0]
    stats = dict(first.stats, parts=[dict(p.stats) for p in parts])
    warnings = list(dict.fromkeys(w for p in parts for w in p.warnings))
    return BRDFSamples(np.concatenate([p.light for p in parts]), first.view,
                       np.concatenate([p.values for p in parts]), np.concatenate([p.transparency for p in parts]),
                       stats, warnings)


def pixel_rays(scene: PeriodicScene, samples: TileSamples, view: np.ndarray, width: int, height: int,
               per_pixel: int, seed: int):
    """The rays of a BTF image seen from ``view``: ``per_pixel`` jittered parallel rays through
    each pixel of the period's texture space (column along X, row 0 at the origin's Y).

    Returns (pixel (R,) int64 row * width + column, corners (R, 3) int32 samples, weights
    (R, 3) float32 barycentric over per_pixel): rays that meet nothing or a face's back are
    left out (black).
    """
    rng = np.random.default_rng(seed)
    pixel = np.repeat(np.arange(width * height), per_pixel)
    jitter = rng.random((2, len(pixel)))
    column = pixel % width
    row = pixel // width
    top = scene.z_range[1] + 0.01 * float(scene.period.max()) + 1e-6
    # Pixel (column, row) is where its rays cross the plane just above the tile's highest
    # point: the image is the tile seen through that plane along -v, as a photograph rectified
    # to it shows a rough sample (a point of height z appears shifted by (top - z) tan(theta_v)).
    points = np.column_stack([scene.origin[0] + (column + jitter[0]) / width * scene.period[0],
                              scene.origin[1] + (row + jitter[1]) / height * scene.period[1],
                              np.full(len(pixel), top)])
    hits = scene.trace(points, np.tile(-view, (len(points), 1)))
    met = np.nonzero(hits.fate == HIT)[0]
    corners, black = seen_corners(samples, hits.triangle[met], -view)
    keep = met[~black]
    return pixel[keep], corners[~black], (hits.barycentric[keep] / per_pixel).astype(np.float32)


def simulate_btf(tile: Tile, lights, views, image_size: tuple[int, int], write, settings: GonioSettings | None = None,
                 per_pixel: int = 4, progress: Callable[[str, float], None] | None = None,
                 part: tuple[int, int] | None = None) -> dict:
    """The tile's BTF: an image per (light, view) pair, rectified to the tile's texture space.

    A pixel's value is pi L / E: the radiance it sends towards the view under a sun of
    irradiance E, times pi (so a white Lambert plane lit from straight above is 1, and
    the images darken as real BTF photographs do when the light tilts; the BRDF is the
    image's mean over pi cos(theta_l)).
    lights (L, 3), views (V, 3): as simulate_brdf; image_size (width, height);
    ``write(light_index, view_index, image (height, width, 3) float32, row 0 at the origin's Y)``
    is called once per pair. Returns the stats.
    part : (index, count), or None: only the pairs of part ``index`` of the run split in
        ``count`` parts by light batches (:func:`part_lights`), each image the same bits as
        in the whole run.
    """
    import time
    settings, module, lights, views = _start(settings, lights, views, sphere=False)
    width, height = (int(v) for v in image_size)
    if not (1 <= width <= 8192 and 1 <= height <= 8192):
        raise AppearanceRefused(f"the image size must be 1 to 8192 pixels a side, got {width} x {height}")
    started = time.perf_counter()

    def report(stage: str, fraction: float) -> None:
        if progress is not None:
            progress(stage, fraction)

    prepared = _prepare(tile, settings, report)
    stats = prepared.stats
    mark = time.perf_counter()
    report("views", 0.2)
    view_rays = [pixel_rays(prepared.scene, prepared.samples, view, width, height, per_pixel, settings.seed + index)
                 for index, view in enumerate(views)]
    stats["views_s"] = round(time.perf_counter() - mark, 3)
    times: dict = {"images_s": 0.0, "write_s": 0.0}
    pixels = width * height
    mine = part_lights(len(lights), light_batch(tile, len(prepared.samples), len(prepared.directions)), part)
    for lit in _light_batches(tile, prepared, lights, settings, module, times, mine):
        b = len(lit.lights)
        for index, view in enumerate(views):
            mark = time.perf_counter()
            pixel, corners, weights = view_rays[index]
            rows, inverse = np.unique(corners, return_inverse=True)
            towards = _outgoing_towards(tile, prepared, lit, view, rows.astype(np.int64), module, settings.threads)
            images = np.zeros((b, pixels, 3))
            kernels.run(module.splat_pixels, settings.threads, pixel, inverse.reshape(corners.shape).astype(np.int64),
                        weights, towards, images)
            images *= np.pi
            times["images_s"] += time.perf_counter() - mark
            mark = time.perf_counter()
            for k in range(b):
                image = images[k].reshape(height, width, 3).astype(np.float32)
                if not np.all(np.isfinite(image)):
                    raise RuntimeError("the BTF simulation produced non-finite values (a bug)")
                write(lit.first + k, index, image)
            times["write_s"] += time.perf_counter() - mark
        report("lights", 0.25 + 0.75 * min(1.0, (lit.first + b - mine.start) / max(len(mine), 1)))
    stats.update({key: round(value, 3) for key, value in times.items()})
    stats["total_s"] = round(time.perf_counter() - started, 3)
    stats["images"] = len(mine) * len(views)
    if part is not None:
        stats["part"] = [int(part[0]), int(part[1])]
    return stats
