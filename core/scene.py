"""Plain data the core works on: meshes, materials, lights, world, settings.

The operators fill these from Blender; tests and benchmarks can build them by hand.
All positions and directions are world space; lengths in scene units.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

LIGHT_KINDS = ("SUN", "POINT", "SPOT", "AREA")
AREA_SHAPES = ("SQUARE", "RECTANGLE", "DISK", "ELLIPSE")


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
    casts_shadow : whether lamps' shadow rays stop at it (Blender's shadow visibility);
        off, it still occludes and reflects light for the table
    terminator_offset : Blender's Shadow Terminator > Geometry Offset: below this cosine to a
        lamp, shadow rays of smooth-shaded faces start lifted towards the smooth surface
        (core.sampling.terminator); 0 turns it off
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
    casts_shadow: bool = True
    terminator_offset: float = 0.1


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
    angle : a sun's angular diameter in radians (0: a hard sun)
    radius : a point or spot lamp's radius (0: a hard point)
    sphere : the lamp is a sphere of ``radius`` (Blender's Soft Falloff off); else Cycles'
        disk of ``radius`` facing each receiver
    casts_shadows : its shadow rays are traced (Blender's ``use_shadow``)
    receivers : names of the only meshes it lights (light linking), None: every mesh
    blockers : names of the only meshes that shadow it (shadow linking), None: every mesh
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
    angle: float = 0.0
    radius: float = 0.0
    sphere: bool = False
    casts_shadows: bool = True
    receivers: tuple[str, ...] | None = None
    blockers: tuple[str, ...] | None = None


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
    suns : list of 'SUN' :class:`Light` the world's own sun discs, taken out of ``image``
        (a Sky Texture's sun); lit as lamps in the world's light group
    """

    color: np.ndarray = field(default_factory=lambda: np.zeros(3))
    image: np.ndarray | None = None
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    light_group: str = ""
    suns: list = field(default_factory=list)


@dataclass
class Scene:
    meshes: list[Mesh]
    lights: list[Light]
    world: World = field(default_factory=World)


