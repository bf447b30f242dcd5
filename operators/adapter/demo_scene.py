"""The built-in demo scene: a closed room lit by a sun through a window and a point light.

Built from code only (bmesh / bpy.data, no operators, no assets), so it works in
background mode and needs no context. What it is meant to exercise:

- colour bleeding: a red and a green wall facing each other, white floor and ceiling;
- indirect light: the sun only enters through the window in the back wall, so most of
  the room is lit by bounces;
- evaluated geometry: Suzanne has a Subdivision Surface modifier (level 1);
- shading normals: Suzanne, the torus and the glowing ball are smooth shaded;
- textured albedo: the pedestal's base colour is a packed 64x64 sRGB checker image,
  looked up through its UV map "UVMap" (non-overlapping, inside [0, 1]);
- emission: a small glowing ball (Principled emission strength 3);
- vertex tables: a finely tessellated dome is baked in vertex mode (its object setting),
  so its results are a colour attribute, the rest are images;
- a black world, so only the lamps and the emitter light the room.

Every material is pure Lambert (Roughness 1, Specular IOR Level 0): with the default
specular layer Cycles' DIFFUSE bake is ~1.4-4% darker than base colour * E / pi,
which would blur the comparison with VisiBake. Albedos are at most 0.8.

The room is 6 x 6 x 3 m inside (x, y in [-3, 3], z in [0, 3]) with 0.2 m thick walls.
The side and end walls run 0.2 m past every seam (down through the floor slab, up
through the ceiling slab, past each other at the corners), so a ray aimed at a seam
always lands inside a face, never between two: no light leaks at the joints.

Only the pedestal has a UV map; the other objects are unwrapped by the bake pipeline.
Object names are stable ("Floor", "WallRed", ...) in a file that does not already hold
objects, meshes or materials of those names.
"""
from __future__ import annotations

import math

import bpy

import bmesh
import numpy as np
from mathutils import Matrix, Vector

from . import compat

__all__ = ["build_demo_scene", "ROOM_HALF", "ROOM_HEIGHT", "WALL"]

ROOM_HALF = 3.0  # interior x, y in [-ROOM_HALF, ROOM_HALF]
ROOM_HEIGHT = 3.0  # interior z in [0, ROOM_HEIGHT]
WALL = 0.2  # thickness of walls, floor and ceiling slabs

# Window in the back wall (y = +ROOM_HALF), interior coordinates.
WINDOW_X = (-1.1, 1.1)
WINDOW_Z = (1.0, 2.2)


def _linear_to_srgb(c: np.ndarray) -> np.ndarray:
    c = np.clip(c, 0.0, 1.0)
    return np.where(c <= 0.0031308, 12.92 * c, 1.055 * np.power(c, 1.0 / 2.4) - 0.055)


def _material(name: str, color, emission=None, strength: float = 0.0) -> bpy.types.Material:
    mat = bpy.data.materials.new(name)
    bsdf = compat.ensure_node_tree(mat).nodes["Principled BSDF"]
    bsdf.inputs["Base Color"].default_value = (*color, 1.0)
    bsdf.inputs["Roughness"].default_value = 1.0
    bsdf.inputs["Specular IOR Level"].default_value = 0.0
    if emission is not None:
        bsdf.inputs["Emission Color"].default_value = (*emission, 1.0)
        bsdf.inputs["Emission Strength"].default_value = strength
    mat.diffuse_color = (*color, 1.0)  # solid-mode viewport colour
    return mat


def _checker_image(name: str, size: int = 64, cells: int = 8) -> bpy.types.Image:
    """An sRGB byte image, packed so it is saved inside the .blend."""
    light = np.array([0.8, 0.8, 0.8])  # linear albedo of the light squares
    dark = np.array([0.1, 0.2, 0.6])  # linear albedo of the dark squares
    ij = np.indices((size, size)) // (size // cells)
    mask = ((ij[0] + ij[1]) % 2 == 0)[..., None]
    rgb = np.where(mask, light, dark)
    # Byte images store encoded values; Cycles decodes sRGB back to these albedos.
    rgba = np.concatenate([_linear_to_srgb(rgb), np.ones((size, size, 1))], axis=2)
    image = bpy.data.images.new(name, size, size, alpha=False, float_buffer=False)
    image.colorspace_settings.name = "sRGB"
    image.pixels.foreach_set(rgba.astype(np.float32).ravel())
    image.update()
    image.pack()
    return image


def _textured_material(name: str, image: bpy.types.Image, uv_map: str) -> bpy.types.Material:
    mat = _material(name, (0.8, 0.8, 0.8))
    nodes, links = mat.node_tree.nodes, mat.node_tree.links
    bsdf = nodes["Principled BSDF"]
    tex = nodes.new("ShaderNodeTexImage")
    tex.image = image
    tex.location = (bsdf.location.x - 320, bsdf.location.y)
    uv = nodes.new("ShaderNodeUVMap")
    uv.uv_map = uv_map
    uv.location = (tex.location.x - 220, tex.location.y)
    links.new(uv.outputs["UV"], tex.inputs["Vector"])
    links.new(tex.outputs["Color"], bsdf.inputs["Base Color"])
    return mat


def _mesh_from_pydata(name: str, verts, faces, smooth: bool = False) -> bpy.types.Mesh:
    """A mesh with outward normals (recalculated: the face lists need not be consistent)."""
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata([tuple(map(float, v)) for v in verts], [], [tuple(map(int, f)) for f in faces])
    bm = bmesh.new()
    bm.from_mesh(mesh)
    bmesh.ops.recalc_face_normals(bm, faces=bm.faces)
    bm.to_mesh(mesh)
    bm.free()
    if smooth:
        mesh.shade_smooth()
    mesh.validate()
    return mesh


def _box(name: str, lo, hi) -> bpy.types.Mesh:
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    verts = [(x, y, z) for z in (z0, z1) for y in (y0, y1) for x in (x0, x1)]
    faces = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    return _mesh_from_pydata(name, verts, faces)


def _wall_with_window(name: str, x, y, z, hole_x, hole_z) -> bpy.types.Mesh:
    """A closed slab x * y * z (thin along y) with a rectangular hole through it."""
    outer = [(x[0], z[0]), (x[1], z[0]), (x[1], z[1]), (x[0], z[1])]
    inner = [(hole_x[0], hole_z[0]), (hole_x[1], hole_z[0]), (hole_x[1], hole_z[1]), (hole_x[0], hole_z[1])]
    verts = []
    for yy in y:
        verts += [(u, yy, w) for u, w in outer] + [(u, yy, w) for u, w in inner]
    faces = []
    for i in range(4):
        j = (i + 1) % 4
        for side in (0, 8):
            faces.append((side + i, side + j, side + 4 + j, side + 4 + i))  # face around the hole
        faces.append((4 + i, 4 + j, 12 + j, 12 + i))  # window reveal
        faces.append((i, j, 8 + j, 8 + i))  # outer rim
    return _mesh_from_pydata(name, verts, faces)


def _torus(name: str, major: float, minor: float, major_segments: int = 32, minor_segments: int = 12):
    u = np.arange(major_segments) * (2 * math.pi / major_segments)
    v = np.arange(minor_segments) * (2 * math.pi / minor_segments)
    uu, vv = np.meshgrid(u, v, indexing="ij")
    ring = major + minor * np.cos(vv)
    verts = np.stack([ring * np.cos(uu), ring * np.sin(uu), minor * np.sin(vv)], axis=-1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(major_segments), np.arange(minor_segments), indexing="ij")
    i1, j1 = (i + 1) % major_segments, (j + 1) % minor_segments
    n = minor_segments
    faces = np.stack([i * n + j, i1 * n + j, i1 * n + j1, i * n + j1], axis=-1).reshape(-1, 4)
    return _mesh_from_pydata(name, verts, faces, smooth=True)


def _bmesh_mesh(name: str, build, smooth: bool = False) -> bpy.types.Mesh:
    bm = bmesh.new()
    build(bm)
    mesh = bpy.data.meshes.new(name)
    bm.to_mesh(mesh)
    bm.free()
    if smooth:
        mesh.shade_smooth()
    return mesh


def _pedestal_mesh(name: str, size: float, uv_map: str) -> bpy.types.Mesh:
    """A cube standing on z = 0 whose six faces are laid out on a 3 x 3 UV grid."""
    half = size / 2.0
    bm = bmesh.new()
    uv_layer = bm.loops.layers.uv.new(uv_map)
    bmesh.ops.create_cube(bm, size=size, matrix=Matrix.Translation((0.0, 0.0, half)))
    pad = 0.02  # keeps texels of neighbouring faces (and the bake's half-texel jitter) apart
    cell = 1.0 / 3.0
    for index, face in enumerate(bm.faces):
        col, row = index % 3, index // 3
        n = face.normal
        axis = max(range(3), key=lambda k: abs(n[k]))
        # Project onto the two axes orthogonal to the face normal.
        a, b = [k for k in range(3) if k != axis]
        for loop in face.loops:
            # The cube spans [-half, half] in x and y and [0, size] in z.
            co = loop.vert.co + Vector((half, half, 0.0))
            s, t = co[a] / size, co[b] / size
            loop[uv_layer].uv = (col * cell + pad + s * (cell - 2 * pad), row * cell + pad + t * (cell - 2 * pad))
    mesh = bpy.data.meshes.new(name)
    bm.to_mesh(mesh)
    bm.free()
    return mesh


def _link(collection, name, data, location=(0.0, 0.0, 0.0), rotation=(0.0, 0.0, 0.0)):
    obj = bpy.data.objects.new(name, data)
    obj.location = location
    obj.rotation_euler = rotation
    collection.objects.link(obj)
    return obj


def build_demo_scene(scene: bpy.types.Scene) -> list[bpy.types.Object]:
    """Build the demo room into ``scene`` and return its mesh objects (the ones to bake).

    Adds a collection "VisiBake Demo" holding 11 meshes (the dome in vertex mode), a sun ("Sun", 5 W/m^2, angle 0,
    through the window), a point light ("PointLight", 200 W, radius 0), a camera
    ("Camera", made the scene camera) and sets a black world ("VisiBake Demo World").
    Nothing else in the scene is touched (apart from the render resolution, 640 x 480).
    """
    collection = bpy.data.collections.new("VisiBake Demo")
    scene.collection.children.link(collection)

    h, t, top = ROOM_HALF, WALL, ROOM_HEIGHT
    white = _material("White", (0.7, 0.7, 0.7))
    red = _material("Red", (0.8, 0.05, 0.05))
    green = _material("Green", (0.05, 0.8, 0.05))

    meshes = []

    def add(name, mesh, mat, **kw):
        mesh.materials.append(mat)
        obj = _link(collection, name, mesh, **kw)
        meshes.append(obj)
        return obj

    add("Floor", _box("Floor", (-h, -h, -t), (h, h, 0.0)), white)
    add("Ceiling", _box("Ceiling", (-h, -h, top), (h, h, top + t)), white)
    add("WallRed", _box("WallRed", (-h - t, -h - t, -t), (-h, h + t, top + t)), red)
    add("WallGreen", _box("WallGreen", (h, -h - t, -t), (h + t, h + t, top + t)), green)
    add("WallBack", _wall_with_window("WallBack", (-h, h), (h, h + t), (-t, top + t), WINDOW_X, WINDOW_Z), white)
    add("WallFront", _box("WallFront", (-h, -h - t, -t), (h, -h, top + t)), white)

    pedestal_size = 0.7
    checker = _checker_image("Checker")
    add("Pedestal", _pedestal_mesh("Pedestal", pedestal_size, "UVMap"),
        _textured_material("Checker", checker, "UVMap"), location=(-1.2, 0.8, 0.0))

    scale = 0.5
    monkey = _bmesh_mesh("Suzanne", lambda bm: bmesh.ops.create_monkey(bm, matrix=Matrix.Scale(scale, 4)),
                         smooth=True)
    z_min = min(v.co.z for v in monkey.vertices)
    suzanne = add("Suzanne", monkey, _material("Orange", (0.8, 0.45, 0.15)),
                  location=(-1.2, 0.8, pedestal_size - z_min))
    subsurf = suzanne.modifiers.new("Subdivision", "SUBSURF")
    subsurf.levels = 1
    subsurf.render_levels = 1

    minor = 0.2
    add("Torus", _torus("Torus", 0.55, minor), _material("Blue", (0.15, 0.25, 0.8)),
        location=(1.3, -0.4, minor))

    # A finely tessellated smooth dome baked with vertex tables (the paper's section 5):
    # its results are the colour attribute VB_lighting, not an image.
    dome = add("Dome", _bmesh_mesh("Dome", lambda bm: bmesh.ops.create_icosphere(bm, subdivisions=4, radius=0.35),
                                   smooth=True), _material("Ivory", (0.75, 0.72, 0.65)), location=(1.4, 1.3, 0.35))
    dome.visibake.mode = "vertex"

    radius = 0.2
    add("GlowBall", _bmesh_mesh("GlowBall", lambda bm: bmesh.ops.create_icosphere(
        bm, subdivisions=3, radius=radius), smooth=True),
        _material("Glow", (0.8, 0.8, 0.8), emission=(1.0, 0.55, 0.2), strength=3.0),
        location=(0.3, 1.9, radius))

    # Sun 35 degrees above the horizon, entering through the window towards -y and
    # turned 25 degrees about z so the patch lands on the floor near the green wall.
    sun = bpy.data.lights.new("Sun", "SUN")
    sun.energy = 5.0
    sun.angle = 0.0
    _link(collection, "Sun", sun, location=(0.0, 6.0, 6.0),
          rotation=(math.radians(-55.0), 0.0, math.radians(25.0)))

    point = bpy.data.lights.new("PointLight", "POINT")
    point.energy = 200.0
    point.shadow_soft_size = 0.0
    _link(collection, "PointLight", point, location=(-0.8, -1.0, 2.5))

    camera = bpy.data.cameras.new("Camera")
    camera.lens = 20.0
    camera.clip_start = 0.05
    scene.camera = _link(collection, "Camera", camera, location=(0.0, -2.85, 1.5),
                         rotation=(math.radians(85.0), 0.0, 0.0))
    scene.render.resolution_x = 640
    scene.render.resolution_y = 480
    scene.render.resolution_percentage = 100

    world = bpy.data.worlds.new("VisiBake Demo World")
    world.color = (0.0, 0.0, 0.0)
    background = compat.ensure_node_tree(world).nodes.get("Background")
    if background is not None:
        background.inputs["Color"].default_value = (0.0, 0.0, 0.0, 1.0)
        background.inputs["Strength"].default_value = 0.0
    scene.world = world
    return meshes
