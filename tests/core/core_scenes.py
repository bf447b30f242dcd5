"""Small hand-built core scenes with exact UV layouts (no xatlas), for analytic tests."""
import numpy as np

from core.scene import Material, Mesh


def quad_mesh(name, corners, uv_rect=(0.0, 0.0, 1.0, 1.0), material=None, resolution=32, output=True):
    """One quad (4 corners, counter-clockwise seen from the front) with a UV rectangle."""
    positions = np.asarray(corners, np.float64)
    triangles = np.array([[0, 1, 2], [0, 2, 3]], np.int32)
    u0, v0, u1, v1 = uv_rect
    uv = np.array([[u0, v0], [u1, v0], [u1, v1], [u0, v1]], np.float32)
    normal = np.cross(positions[1] - positions[0], positions[3] - positions[0])
    normal /= np.linalg.norm(normal)
    return Mesh(name=name, positions=positions, triangles=triangles,
                corner_normals=np.tile(normal.astype(np.float32), (2, 3, 1)),
                material_index=np.zeros(2, np.int32), materials=[material or Material()],
                uv_maps={"UVMap": uv[triangles]}, bake_uv_map="UVMap",
                resolution=(resolution, resolution), output=output)


def box_interior(size=1.0, material=None, resolution=48):
    """A closed cube seen from inside: six faces with normals pointing inwards,
    each in its own cell of a 3 x 2 UV grid with a gutter between cells."""
    s = size / 2
    outward = [  # counter-clockwise seen from outside; reversed below to face inwards
        [(-s, -s, -s), (-s, s, -s), (s, s, -s), (s, -s, -s)],    # z = -s
        [(-s, -s, s), (s, -s, s), (s, s, s), (-s, s, s)],        # z = +s
        [(-s, -s, -s), (s, -s, -s), (s, -s, s), (-s, -s, s)],    # y = -s
        [(-s, s, -s), (-s, s, s), (s, s, s), (s, s, -s)],        # y = +s
        [(-s, -s, -s), (-s, -s, s), (-s, s, s), (-s, s, -s)],    # x = -s
        [(s, -s, -s), (s, s, -s), (s, s, s), (s, -s, s)],        # x = +s
    ]
    faces = [face[::-1] for face in outward]
    positions, triangles, uv, normals = [], [], [], []
    gap = 0.04
    for index, face in enumerate(faces):
        col, row = index % 3, index // 3
        u0, v0 = col / 3 + gap, row / 2 + gap
        u1, v1 = (col + 1) / 3 - gap, (row + 1) / 2 - gap
        base = len(positions)
        positions.extend(face)
        quad = np.array([[0, 1, 2], [0, 2, 3]]) + base
        triangles.extend(quad.tolist())
        rect = [(u0, v0), (u1, v0), (u1, v1), (u0, v1)]
        uv.extend([[rect[0], rect[1], rect[2]], [rect[0], rect[2], rect[3]]])
        p = np.array(face, float)
        n = np.cross(p[1] - p[0], p[3] - p[0])
        n /= np.linalg.norm(n)
        normals.extend([[n, n, n]] * 2)
    return Mesh(name="Box", positions=np.array(positions, float), triangles=np.array(triangles, np.int32),
                corner_normals=np.array(normals, np.float32), material_index=np.zeros(12, np.int32),
                materials=[material or Material()], uv_maps={"UVMap": np.array(uv, np.float32)},
                bake_uv_map="UVMap", resolution=(resolution, resolution))


def grid_mesh(name, size=2.0, segments=8, z=0.0, material=None, mode="vertex", flip=False, resolution=32):
    """A square grid in the plane z, facing +z (or -z with ``flip``), smooth normals."""
    coords = np.linspace(-size / 2, size / 2, segments + 1)
    xs, ys = np.meshgrid(coords, coords)
    positions = np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, z)], axis=1)
    triangles = []
    for row in range(segments):
        for col in range(segments):
            a = row * (segments + 1) + col
            b, c, d = a + 1, a + segments + 2, a + segments + 1
            triangles += [[a, b, c], [a, c, d]]
    triangles = np.array(triangles, np.int32)
    if flip:
        triangles = triangles[:, ::-1].copy()
    normal = np.array([0.0, 0.0, -1.0 if flip else 1.0], np.float32)
    uv = ((positions[:, :2] / size) + 0.5).astype(np.float32)
    return Mesh(name=name, positions=positions, triangles=triangles,
                corner_normals=np.tile(normal, (len(triangles), 3, 1)),
                material_index=np.zeros(len(triangles), np.int32), materials=[material or Material()],
                uv_maps={"UVMap": uv[triangles]}, bake_uv_map="UVMap", resolution=(resolution, resolution),
                mode=mode, vertex_count=len(positions), corner_loops=np.arange(3 * len(triangles)).reshape(-1, 3),
                loop_count=3 * len(triangles))
