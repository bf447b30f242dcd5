"""The box Cycles' bake averages each texel over, and the texels it bakes, in this Blender.

    .venv/bin/python benchmarks/bake_footprint.py                  # the default Blender
    .venv-bpy5.3.0/bin/python benchmarks/bake_footprint.py         # any other venv
    PYTHONPATH=/tmp/bpy521 .venv-bpy5.3.0/bin/python benchmarks/bake_footprint.py   # a bpy unpacked there

Footprint: a 0.2 m emissive square 1 cm above a 1 m plane, baked by Cycles (DIFFUSE, direct
light only, ``--samples``) at 32^2, against Lambert's polygon form factor averaged over a box
of each width around every texel centre. The width with the lowest RMS is the bake's (half a
texel up to Blender 5.2.0, the whole texel from 5.2.1: docs/reliability.md).
Coverage: a triangle whose UVs cut through texels, baked with margin 0: the texels baked
against those whose centre it covers (equal up to 5.2; 5.3 also bakes the touched ones).
"""
import argparse
import os
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

RESOLUTION = 32
HEIGHT = 0.01
HALF_SIZE = 0.1
STRENGTH = 10.0


def form_factor(point, polygon):
    """Lambert's form factor from ``point`` (3,) (normal +z) to ``polygon`` (n, 3)."""
    import numpy as np

    v = polygon - point
    v = v / np.linalg.norm(v, axis=1, keepdims=True)
    total = 0.0
    for i in range(len(v)):
        a, b = v[i], v[(i + 1) % len(v)]
        cross = np.cross(a, b)
        sine = np.linalg.norm(cross)
        total += np.arctan2(sine, np.dot(a, b)) * cross[2] / sine
    return abs(total) / (2 * np.pi)


def box_average(width: float, points: int = 8):
    """(RESOLUTION, RESOLUTION) the square's light averaged over each texel's box ``width`` wide."""
    import numpy as np

    polygon = np.array([[-HALF_SIZE, -HALF_SIZE, HEIGHT], [HALF_SIZE, -HALF_SIZE, HEIGHT],
                        [HALF_SIZE, HALF_SIZE, HEIGHT], [-HALF_SIZE, HALF_SIZE, HEIGHT]])
    centres = (np.arange(RESOLUTION) + 0.5) / RESOLUTION - 0.5
    offsets = ((np.arange(points) + 0.5) / points - 0.5) * width / RESOLUTION
    return np.array([[np.mean([STRENGTH * form_factor(np.array([x + dx, y + dy, 0.0]), polygon)
                               for dx in offsets for dy in offsets]) for x in centres] for y in centres])


def _quad(name, corners, uv=True):
    import bpy

    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata(corners, [], [tuple(range(len(corners)))])
    mesh.update()
    if uv:
        layer = mesh.uv_layers.new(name="UVMap")
        for loop, (x, y, _) in zip(layer.data, corners):
            loop.uv = (x + 0.5, y + 0.5) if len(corners) == 4 else (x, y)
    obj = bpy.data.objects.new(name, mesh)
    bpy.context.scene.collection.objects.link(obj)
    return obj


def _material(obj, emission=None):
    import bpy

    from tools.blender_compat import compat

    material = bpy.data.materials.new(obj.name)
    tree = compat.ensure_node_tree(material)
    tree.nodes.clear()
    output = tree.nodes.new("ShaderNodeOutputMaterial")
    if emission is None:
        shader = tree.nodes.new("ShaderNodeBsdfDiffuse")
        shader.inputs["Color"].default_value = (1.0, 1.0, 1.0, 1.0)
    else:
        shader = tree.nodes.new("ShaderNodeEmission")
        shader.inputs["Strength"].default_value = emission
    tree.links.new(shader.outputs[0], output.inputs[0])
    obj.data.materials.append(material)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=1024)
    args = parser.parse_args(argv)

    import bpy

    import numpy as np

    from tools.cycles_bake import bake_diffuse

    bpy.ops.wm.read_factory_settings(use_empty=True)
    plane = _quad("Plane", [(-0.5, -0.5, 0.0), (0.5, -0.5, 0.0), (0.5, 0.5, 0.0), (-0.5, 0.5, 0.0)])
    _material(plane)
    h = HALF_SIZE
    square = _quad("Square", [(-h, -h, HEIGHT), (-h, h, HEIGHT), (h, h, HEIGHT), (h, -h, HEIGHT)], uv=False)
    _material(square, STRENGTH)
    baked = bake_diffuse([plane], "UVMap", RESOLUTION, RESOLUTION, bounces=0, samples=args.samples,
                         pass_filter=("DIRECT",))["Plane"][..., 0]
    print(f"Blender {bpy.app.version_string}: RMS of Cycles' texels against the closed form over a box of width")
    for width in (0.5, 0.75, 1.0):
        rms = float(np.sqrt(np.mean((baked - box_average(width)) ** 2)))
        print(f"  {width:.2f} texel: {rms:.4f}")

    bpy.ops.wm.read_factory_settings(use_empty=True)
    corners = [(0.13, 0.07, 0.0), (0.91, 0.23, 0.0), (0.37, 0.88, 0.0)]
    triangle = _quad("Triangle", corners)
    _material(triangle)
    world = bpy.data.worlds.new("White")
    world.color = (1.0, 1.0, 1.0)
    bpy.context.scene.world = world
    alpha = bake_diffuse([triangle], "UVMap", RESOLUTION, RESOLUTION, bounces=0, samples=1,
                         pass_filter=("DIRECT",))["Triangle"][..., 3]
    centres = (np.arange(RESOLUTION) + 0.5) / RESOLUTION
    x, y = np.meshgrid(centres, centres)
    uv = np.array(corners)[:, :2]
    inside = np.ones_like(x, bool)
    for i in range(3):
        a, b = uv[i], uv[(i + 1) % 3]
        inside &= (b[0] - a[0]) * (y - a[1]) - (b[1] - a[1]) * (x - a[0]) >= 0
    print(f"  coverage: {int((alpha > 0).sum())} texels baked, {int(inside.sum())} texel centres inside the triangle")
    return 0


if __name__ == "__main__":
    status = main()
    from tools.blender_compat import compat

    compat.end_module_process(status)
