"""Plain data the core works on: meshes, materials, lights, world, settings.

The operators fill these from Blender; tests and benchmarks can build them by hand.
All positions and directions are world space; lengths in scene units.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

PASSES = ("lighting", "direct", "indirect", "irradiance", "ao")
SHADOW_MODES = ("fractions", "exact")
LIGHT_KINDS = ("SUN", "POINT", "SPOT", "AREA")
AREA_SHAPES = ("SQUARE", "RECTANGLE", "DISK", "ELLIPSE")
SAMPLE_MODES = ("atlas", "vertex")
VERTEX_LOOKUPS = ("interpolate", "nearest")


@dataclass
class Material:
    """A Lambert material: albedo rho and emitted radiance.

    base_color : (3,) float  linear RGB albedo used where there is no texture
    base_color_texture : (h, w, 3) float32 or None, linear RGB, row 0 at v = 0
    texture_uv_map : name of the mesh UV map the texture is looked up with
    emission : (3,) float  emitted radiance (colour * strength), W/(m^2 sr) in Cycles' units
    """

    name: str = "default"
    base_color: np.ndarray = field(default_factory=lambda: np.full(3, 0.8))
    base_color_texture: np.ndarray | None = None
    texture_uv_map: str | None = None
    emission: np.ndarray = field(default_factory=lambda: np.zeros(3))


@dataclass
class Mesh:
    """One evaluated, triangulated mesh object in world space.

    positions : (n, 3) float64
    triangles : (m, 3) int32, counter-clockwise seen from the front
    corner_normals : (m, 3, 3) float32 shading normals per triangle corner
    material_index : (m,) int32 into ``materials``
    uv_maps : name -> (m, 3, 2) float32 UV per triangle corner
    bake_uv_map : the UV map the atlas uses (must be a key of uv_maps)
    resolution : (width, height) of the atlas in texels
    output : whether this object gets output images (False: it only occludes
        and reflects light, through an atlas that is never written)
    light_group : the light group its emission belongs to ('' : the object's name)
    mode : 'atlas' (samples are texels of the bake UV map) or 'vertex' (samples are
        vertices, or corners where split normals differ; the paper's section 5)
    corner_loops : (m, 3) int64 the base mesh's loop (face corner) of each triangle
        corner, for results on the corner domain; None where unknown
    vertex_count, loop_count : sizes of the base mesh's point and corner domains
    """

    name: str
    positions: np.ndarray
    triangles: np.ndarray
    corner_normals: np.ndarray
    material_index: np.ndarray
    materials: list[Material]
    uv_maps: dict[str, np.ndarray]
    bake_uv_map: str
    resolution: tuple[int, int]
    output: bool = True
    light_group: str = ""
    mode: str = "atlas"
    corner_loops: np.ndarray | None = None
    vertex_count: int = 0
    loop_count: int = 0


@dataclass
class Light:
    """A lamp in Cycles' units.

    kind : 'SUN' | 'POINT' | 'SPOT' | 'AREA'
    color : (3,) float linear RGB
    strength : sun irradiance at normal incidence (W/m^2), else power in W
    position : (3,) float (unused for suns)
    direction : (3,) float unit vector the light travels along (the lamp's -Z)
    spot_size : full cone angle in radians; spot_blend in [0, 1]
    area_shape, size_x, size_y : area light shape and extent
    axis_x, axis_y : (3,) float the area light's local X and Y axes (world space, unit)
    group : the light group it belongs to ('' : its own, named after the lamp)
    """

    name: str
    kind: str
    color: np.ndarray
    strength: float
    position: np.ndarray = field(default_factory=lambda: np.zeros(3))
    direction: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, -1.0]))
    spot_size: float = np.pi / 4
    spot_blend: float = 0.15
    area_shape: str = "SQUARE"
    size_x: float = 1.0
    size_y: float = 1.0
    axis_x: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0]))
    axis_y: np.ndarray = field(default_factory=lambda: np.array([0.0, 1.0, 0.0]))
    group: str = ""


@dataclass
class World:
    """Environment radiance seen by rays that leave the scene, in Cycles' units.

    color : (3,) float uniform radiance (colour * strength of the Background node),
        used where there is no image
    image : (h, w, 3) float32 or None, linear RGB radiance of an equirectangular
        environment (strength already applied), row 0 at the bottom (Blender's order)
    rotation : (3, 3) float64 world-to-texture rotation applied to a direction before
        the equirectangular lookup (a Mapping node's rotation), identity if none
    light_group : the light group of world light ('' : "world")
    """

    color: np.ndarray = field(default_factory=lambda: np.zeros(3))
    image: np.ndarray | None = None
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    light_group: str = ""


@dataclass
class Scene:
    meshes: list[Mesh]
    lights: list[Light]
    world: World = field(default_factory=World)


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
