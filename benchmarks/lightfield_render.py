"""Seconds per light field view: the GPU renderer (gpu_shaders.lightfield) and its CPU twin.

    .venv/bin/python benchmarks/lightfield_render.py [--views 12] [--cpu-views 2] [--out FILE.json]

Two baked scenes, built from arrays (no .blend):

- "50k": ~50k triangles with one 1024^2 lighting atlas: a 144 x 144 quad terrain and four
  boxes textured through the atlas (one draw), a 96 x 48 vertex-lit sphere (per-corner radiance)
  and a 512 x 256 equirectangular sky where no surface is. The camera looks down at the terrain
  with the horizon in view, so every pass (textured, vertex-lit, world) has work.
- "demo": the demo scene's size (operators/adapter/demo_scene.py: ~11k triangles in 11
  objects, the icosphere dome vertex-lit): a closed 6 x 6 x 3 m room of six 16 x 16-quad walls
  and four UV spheres, each with its own 512^2 lighting image (10 draws), a 5k-triangle
  vertex-lit dome, and the black world (uniform: no world pass); seen from inside.

For each scene, size (256^2, 512^2) and supersampling (2, 3) with Cycles' 1.5 px
Blackman-Harris filter: the setup (upload) time and the mean seconds per view over ``--views``
views of a 16 x 16 HCI grid (the first view, which compiles the shaders, is timed apart), the
same with the depth read back, and the CPU twin (embree) on ``--cpu-views`` views (50k scene
only). Also the projected time of a 16 x 16 grid at 256^2 and a 9 x 9 grid at 512^2 (the
targets: 5 s and 10 s).

Needs a GPU context (Mesa's llvmpipe will do: then the "GPU" runs on the CPU cores too).
"""
import argparse
import os
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

import numpy as np  # noqa: E402

SIZES = (256, 512)
SUPERSAMPLING = (2, 3)
FILTER_WIDTH = 1.5


def _grid_mesh(function, nu: int, nv: int):
    """Triangles (unshared corners) of a (nu x nv)-quad parametric surface and its UVs in [0, 1]^2.

    function maps (u, v) arrays in [0, 1] to (..., 3) points."""
    u, v = np.meshgrid(np.linspace(0, 1, nu + 1), np.linspace(0, 1, nv + 1))
    points = function(u, v).reshape(-1, 3)
    uv = np.stack([u, v], -1).reshape(-1, 2)
    i, j = np.meshgrid(np.arange(nu), np.arange(nv))
    a = (j * (nu + 1) + i).ravel()
    b, c = a + 1, a + nu + 1
    d = c + 1
    triangles = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    return points[triangles].reshape(-1, 3), uv[triangles].reshape(-1, 2)


def synthetic_scene(lfscene):
    """(DrawScene, triangle count): terrain + boxes in one atlas, a vertex-lit sphere, a sky."""
    rng = np.random.default_rng(7)
    size = 1024
    y, x = np.mgrid[:size, :size] / size
    atlas = np.stack([0.5 + 0.4 * np.sin(40 * x) * np.cos(30 * y), 0.3 + 0.2 * x, 0.2 + 0.6 * y], -1)
    atlas = (atlas + 0.05 * rng.random((size, size, 3))).astype(np.float32)

    def terrain(u, v):
        px, py = 8 * u - 4, 8 * v - 4
        return np.stack([px, py, 0.3 * np.sin(2 * px) * np.cos(1.5 * py)], -1)

    positions, uv = _grid_mesh(terrain, 144, 144)
    uv = uv * 0.75  # the terrain's island of the atlas
    meshes = [lfscene.DrawMesh(positions, np.zeros_like(positions), uv, atlas)]
    for number, centre in enumerate(((-2, 1, 0.5), (2, 1.5, 0.5), (-1, -2, 0.5), (2.5, -1.5, 0.5))):
        corners = np.array([[x, y, z] for z in (-0.5, 0.5) for y in (-0.5, 0.5) for x in (-0.5, 0.5)])
        faces = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
        triangles = np.array([t for f in faces for t in ((f[0], f[1], f[2]), (f[0], f[2], f[3]))])
        box = (corners[triangles].reshape(-1, 3) + centre).astype(np.float32)
        box_uv = 0.76 + 0.05 * number + 0.04 * rng.random((len(box), 2))
        meshes.append(lfscene.DrawMesh(box, np.zeros_like(box), box_uv, atlas))

    def sphere(u, v):
        theta, phi = np.pi * v, 2 * np.pi * u
        return np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], -1) + [0, 0, 1.2]

    ball, _ = _grid_mesh(sphere, 96, 48)
    glow = (0.5 + 0.5 * ball[:, [2, 0, 1]] / 2.2).clip(0, None)
    meshes.append(lfscene.DrawMesh(ball, glow))
    theta = np.linspace(0, 1, 256)[:, None, None]
    sky = np.broadcast_to(np.concatenate([0.2 + theta, 0.4 + theta, 0.9 + 0 * theta], -1), (256, 512, 3))
    scene = lfscene.DrawScene(meshes, np.ascontiguousarray(sky, np.float32))
    return scene, sum(m.triangle_count for m in meshes)


def demo_like_scene(lfscene):
    """(DrawScene, triangle count) of the demo scene's size, one 512^2 image per textured object."""
    rng = np.random.default_rng(3)
    meshes = []

    def image():
        base = rng.random(3) * 0.8 + 0.1
        y, x = np.mgrid[:512, :512] / 512.0
        return (base * (0.6 + 0.4 * np.sin(6 * x + 3 * y))[..., None]).astype(np.float32)

    walls = [  # (origin, u axis, v axis) of each 6 x 6 or 6 x 3 wall
        ((-3, -3, 0), (6, 0, 0), (0, 6, 0)), ((-3, -3, 3), (6, 0, 0), (0, 6, 0)),
        ((-3, -3, 0), (0, 6, 0), (0, 0, 3)), ((3, -3, 0), (0, 6, 0), (0, 0, 3)),
        ((-3, -3, 0), (6, 0, 0), (0, 0, 3)), ((-3, 3, 0), (6, 0, 0), (0, 0, 3))]
    for origin, u_axis, v_axis in walls:
        def wall(u, v, o=origin, a=u_axis, b=v_axis):
            return np.asarray(o) + u[..., None] * np.asarray(a) + v[..., None] * np.asarray(b)

        positions, uv = _grid_mesh(wall, 16, 16)
        meshes.append(lfscene.DrawMesh(positions, np.zeros_like(positions), uv, image()))
    for centre in ((-1.5, 1.0, 0.6), (1.5, 1.0, 0.6), (0.0, 1.5, 1.5), (-1.0, -0.5, 0.4)):
        def ball(u, v, c=centre):
            theta, phi = np.pi * v, 2 * np.pi * u
            return 0.4 * np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], -1) + c

        positions, uv = _grid_mesh(ball, 32, 16)
        meshes.append(lfscene.DrawMesh(positions, np.zeros_like(positions), uv, image()))

    def dome(u, v):
        theta, phi = 0.5 * np.pi * v, 2 * np.pi * u
        return 0.35 * np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], -1) + [
            1.2, -0.8, 0.0]

    positions, _ = _grid_mesh(dome, 64, 40)
    meshes.append(lfscene.DrawMesh(positions, (0.3 + 0.2 * positions[:, [2, 0, 1]]).clip(0, None)))
    scene = lfscene.DrawScene(meshes, np.zeros((1, 1, 3), np.float32))
    return scene, sum(m.triangle_count for m in meshes)


def views_for(cameras, size: int):
    """A 16 x 16 HCI grid around a camera 9 m from the scene, looking 35 degrees down."""
    tilt = np.radians(55.0)
    rotation = cameras.rotation_from_euler_xyz(tilt, 0.0, 0.0)
    camera = cameras.CentreCamera(position_m=[0.0, -7.5, 5.0], rotation=rotation, focal_length_mm=35.0,
                                  sensor_size_mm=36.0, resolution_x_px=size, resolution_y_px=size)
    grid = cameras.LightFieldGrid(16, 16, 50.0, 9.0)
    return cameras.grid_views(camera, grid, 0.1, 100.0)


def demo_views_for(cameras, size: int):
    """A 16 x 16 HCI grid around a camera inside the room, looking at the back wall."""
    rotation = cameras.rotation_from_euler_xyz(np.radians(80.0), 0.0, 0.0)
    camera = cameras.CentreCamera(position_m=[0.0, -2.7, 1.6], rotation=rotation, focal_length_mm=24.0,
                                  sensor_size_mm=36.0, resolution_x_px=size, resolution_y_px=size)
    grid = cameras.LightFieldGrid(16, 16, 20.0, 4.0)
    return cameras.grid_views(camera, grid, 0.1, 100.0)


def _time_views(renderer, views, want_depth=False) -> float:
    started = time.perf_counter()
    for view in views:
        renderer.render(view.view_matrix, view.projection_matrix, 0.1, 100.0, want_depth=want_depth)
    return (time.perf_counter() - started) / len(views)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--views", type=int, default=12, help="views timed per setting (GPU)")
    parser.add_argument("--cpu-views", type=int, default=2, help="views timed per setting (CPU twin; 0: skip)")
    parser.add_argument("--out", default=None, help="also write the figures as JSON here")
    args = parser.parse_args(argv)

    from tools.visibake import load_extension

    extension = load_extension()
    import importlib

    lfscene = importlib.import_module(f"{extension.__name__}.core.lightfield.scene")
    cameras = importlib.import_module(f"{extension.__name__}.core.lightfield.cameras")
    raycast = importlib.import_module(f"{extension.__name__}.core.lightfield.raycast")
    runtime = importlib.import_module(f"{extension.__name__}.gpu_shaders.runtime")
    gpu_lightfield = importlib.import_module(f"{extension.__name__}.gpu_shaders.lightfield")
    info = runtime.device_info()
    print(f"GPU: {info.renderer} ({info.backend}); {os.cpu_count()} CPU cores; "
          f"load average before: {os.getloadavg()[0]:.2f}")
    rows = []
    for name, build, make_views, cpu_views in (("50k", synthetic_scene, views_for, args.cpu_views),
                                               ("demo", demo_like_scene, demo_views_for, 0)):
        scene, triangles = build(lfscene)
        print(f"scene {name}: {triangles} triangles in {len(scene.meshes)} meshes, "
              f"{sum(m.image is not None for m in scene.meshes)} images")
        for size in SIZES:
            views = make_views(cameras, size)
            for s in SUPERSAMPLING:
                started = time.perf_counter()
                renderer = gpu_lightfield.ViewRenderer(scene, size, size, s, FILTER_WIDTH)
                setup = time.perf_counter() - started
                first = _time_views(renderer, views[:1])
                per_view = _time_views(renderer, views[1:1 + args.views])
                with_depth = _time_views(renderer, views[1:1 + max(1, args.views // 3)], want_depth=True)
                renderer.close()
                cpu = None
                if cpu_views > 0:
                    twin = raycast.RaycastRenderer(scene, size, size, s, FILTER_WIDTH)
                    cpu = _time_views(twin, views[:cpu_views])
                rows.append({"scene": name, "triangles": triangles, "size": size, "supersampling": s,
                             "setup_s": setup, "first_view_s": first, "gpu_view_s": per_view,
                             "gpu_view_with_depth_s": with_depth, "cpu_view_s": cpu})
    print(f"\n{'scene':>5} {'view':>9} {'s':>2} {'setup s':>8} {'1st view s':>10} {'GPU s/view':>10} {'+depth':>8} "
          f"{'CPU s/view':>10} {'grid':>6} {'grid s (GPU)':>12}")
    for row in rows:
        count = 256 if row["size"] == 256 else 81
        grid = "16x16" if count == 256 else "9x9"
        cpu = f"{row['cpu_view_s']:10.3f}" if row["cpu_view_s"] is not None else f"{'-':>10}"
        print(f"{row['scene']:>5} {row['size']:>4}x{row['size']:<4} {row['supersampling']:>2} {row['setup_s']:8.3f} "
              f"{row['first_view_s']:10.3f} {row['gpu_view_s']:10.4f} {row['gpu_view_with_depth_s']:8.4f} {cpu} "
              f"{grid:>6} {row['setup_s'] + count * row['gpu_view_s']:12.2f}")
    print(f"load average after: {os.getloadavg()[0]:.2f}")
    if args.out:
        from benchmarks.run import write_results

        write_results(args.out, {"renderer": info.renderer, "rows": rows})
    return 0


if __name__ == "__main__":
    status = main()
    from tools.blender_compat import compat

    compat.end_module_process(status)
