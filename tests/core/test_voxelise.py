"""A closed mesh's interior as voxel fractions (core.volume.voxelise) against exact volumes.

Meshes are built here with numpy: a cube (12 triangles), an icosphere (subdivided
icosahedron) and a bumpy UV sphere. Their exact volume is the polyhedron's own, by the
divergence theorem (the sum of the signed tetrahedra on the origin), not the smooth sphere's.

Tolerances. The voxelised volume counts stratified samples: each sample stands for a cube
of side d = h / s (h the voxel's side, s samples per axis), and only the sample cubes that
straddle the surface can be wrong, each by at most d^3 / 2 on average in the worst case.
Where the surface is aligned with the voxel faces (the cube on its fitted grid), none
straddles it and the count is exact. For a sphere, which cuts the sample cubes at every
offset, the errors have both signs: about A / d^2 straddling cubes (A the area) of random
sign give an expected error of order d^3 sqrt(A / d^2), 1e-3 of the icosphere's volume
here. A systematic error, such as a lost or an extra half-layer of samples over the whole
surface (a wrong parity at the surface, an off-by-half in the sample positions), moves it by
A d / 2, over 2 %. ``SPHERE_TOLERANCE`` = 0.5 % sits between the two.
"""
from __future__ import annotations

import numpy as np
import pytest

from core.visibility.rays import RayScene
from core.volume.voxelise import fitted_grid, inside_fraction

SPHERE_TOLERANCE = 0.005


def cube(half=1.0, centre=(0.0, 0.0, 0.0)):
    """(8, 3) float64 corners of an axis-aligned cube and its (12, 3) outward-wound triangles."""
    bits = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], np.float64)
    vertices = (2.0 * bits - 1.0) * half + np.asarray(centre, np.float64)
    # Corner i = 4x + 2y + z; each face as a quad counter-clockwise seen from outside.
    quads = [(0, 1, 3, 2), (4, 6, 7, 5),   # x = -, x = +
             (0, 4, 5, 1), (2, 3, 7, 6),   # y = -, y = +
             (0, 2, 6, 4), (1, 5, 7, 3)]   # z = -, z = +
    triangles = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))], np.int64)
    return vertices, triangles


CUBE_FACE = {"-x": [0, 1], "+x": [2, 3], "-y": [4, 5], "+y": [6, 7], "-z": [8, 9], "+z": [10, 11]}


def icosphere(level: int, radius=1.0):
    """A subdivided icosahedron on the sphere of ``radius``: 20 * 4^level triangles."""
    p = (1.0 + 5 ** 0.5) / 2.0
    vertices = np.array([(-1, p, 0), (1, p, 0), (-1, -p, 0), (1, -p, 0), (0, -1, p), (0, 1, p),
                         (0, -1, -p), (0, 1, -p), (p, 0, -1), (p, 0, 1), (-p, 0, -1), (-p, 0, 1)], np.float64)
    vertices /= np.linalg.norm(vertices, axis=1, keepdims=True)
    faces = np.array([(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4),
                      (11, 10, 2), (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8),
                      (3, 8, 9), (4, 9, 5), (2, 4, 11), (6, 2, 10), (8, 6, 7), (9, 8, 1)], np.int64)
    for _ in range(level):
        edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
        unique, inverse = np.unique(edges, axis=0, return_inverse=True)
        middle = vertices[unique].mean(axis=1)
        middle /= np.linalg.norm(middle, axis=1, keepdims=True)
        ab, bc, ca = (inverse.reshape(3, -1) + len(vertices))
        vertices = np.vstack([vertices, middle])
        a, b, c = faces.T
        faces = np.concatenate([np.stack(t, axis=1) for t in ((a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca))])
    return vertices * radius, faces


def bumpy_sphere(around=100, rings=51):
    """A UV sphere with bumps (radius 1 +- 0.2): 2 * around * (rings - 1) triangles, several
    crossings per line."""
    theta = np.arange(around) * 2 * np.pi / around
    phi = np.linspace(0.0, np.pi, rings)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    radius = 1.0 + 0.2 * np.sin(5 * t) * np.sin(4 * p)
    vertices = np.stack([radius * np.sin(p) * np.cos(t), radius * np.sin(p) * np.sin(t), radius * np.cos(p)],
                        axis=-1).reshape(-1, 3)
    i, j = np.arange(around)[:, None], np.arange(rings - 1)[None]
    a, b = i * rings + j, (i + 1) % around * rings + j
    c, d = (i + 1) % around * rings + j + 1, i * rings + j + 1
    triangles = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    return vertices, triangles


def mesh_volume(vertices, triangles) -> float:
    """The polyhedron's volume (divergence theorem), whatever its winding."""
    a, b, c = (vertices[triangles[:, k]] for k in range(3))
    return abs(float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum()) / 6.0)


def voxel_volume(matrix) -> float:
    return abs(float(np.linalg.det(np.asarray(matrix)[:3, :3])))


def voxelised_volume(fractions, matrix) -> float:
    return float(fractions.sum(dtype=np.float64)) * voxel_volume(matrix)


def rotation(axis, angle) -> np.ndarray:
    axis = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def affine(linear, offset) -> np.ndarray:
    matrix = np.eye(4)
    matrix[:3, :3] = linear
    matrix[:3, 3] = offset
    return matrix


# ----------------------------------------------------------------------------- fitted_grid

def test_fitted_grid_covers_the_box_with_cubic_voxels_resolution_along_its_longest_side():
    low, high = np.array([-1.0, 2.0, 0.5]), np.array([3.0, 3.0, 2.5])  # sides 4, 1, 2
    shape, matrix = fitted_grid(low, high, 34)
    assert shape == (34, 10, 18)   # 32 voxels of 0.125 span 4, 8 span 1, 16 span 2; + 2 margins each
    assert matrix.dtype == np.float64 and matrix.shape == (4, 4)
    np.testing.assert_allclose(matrix[:3, :3], np.eye(3) * 0.125)
    np.testing.assert_allclose(matrix[3], [0, 0, 0, 1])
    # The grid's outer faces lie a margin voxel outside the box, on every side.
    first = matrix @ np.array([-0.5, -0.5, -0.5, 1.0])
    last = matrix @ np.array([*(np.array(shape) - 0.5), 1.0])
    np.testing.assert_allclose(first[:3], low - 0.125)
    np.testing.assert_allclose(last[:3], high + 0.125)


def test_fitted_grid_centres_a_side_that_is_not_a_multiple_of_the_voxel_and_gives_a_flat_box_one_voxel():
    shape, matrix = fitted_grid([0, 0, 0], [1.0, 0.3, 0.0], 12, margin_voxels=1)
    voxel = 1.0 / 10
    assert shape == (12, 3 + 2, 1 + 2)
    centre = matrix @ np.array([*((np.array(shape) - 1) / 2.0), 1.0])
    np.testing.assert_allclose(centre[:3], [0.5, 0.15, 0.0])
    assert matrix[0, 0] == pytest.approx(voxel)


def test_fitted_grid_shrinks_the_margin_where_the_resolution_leaves_no_room_and_refuses_an_empty_box():
    shape, matrix = fitted_grid([0, 0, 0], [1, 1, 1], 2, margin_voxels=1)
    assert shape == (2, 2, 2) and matrix[0, 0] == pytest.approx(0.5)
    shape, _ = fitted_grid([0, 0, 0], [1, 1, 1], 8, margin_voxels=0)
    assert shape == (8, 8, 8)
    with pytest.raises(ValueError):
        fitted_grid([0, 0, 0], [0, 0, 0], 16)
    with pytest.raises(ValueError):
        fitted_grid([0, 0, np.nan], [1, 1, 1], 16)
    with pytest.raises(ValueError):
        fitted_grid([0, 0, 0], [1, 1, 1], 0)


# ----------------------------------------------------------------------------- inside_fraction

def test_a_cube_on_its_fitted_grid_is_exact():
    """The faces lie on voxel faces: every voxel is wholly in or out, the volume exact."""
    vertices, triangles = cube(half=1.0, centre=(0.3, -2.0, 5.0))
    shape, matrix = fitted_grid(vertices.min(axis=0), vertices.max(axis=0), 32)
    fractions = inside_fraction(vertices, triangles, matrix, shape)
    assert fractions.shape == shape == (32, 32, 32) and fractions.dtype == np.float32
    assert voxelised_volume(fractions, matrix) == pytest.approx(8.0, rel=1e-6)
    assert np.all(fractions[1:-1, 1:-1, 1:-1] == 1.0)
    assert fractions.sum() == 30 ** 3   # the margin is empty


@pytest.mark.parametrize("samples", [1, 2, 3])
def test_fractions_are_multiples_of_the_sample_count_and_the_aligned_cube_stays_exact(samples):
    vertices, triangles = cube()
    shape, matrix = fitted_grid(vertices.min(axis=0), vertices.max(axis=0), 12)
    fractions = inside_fraction(vertices, triangles, matrix, shape, samples_per_axis=samples)
    steps = fractions * samples ** 3
    np.testing.assert_allclose(steps, np.round(steps), atol=1e-4)
    assert voxelised_volume(fractions, matrix) == pytest.approx(8.0, rel=1e-6)


def test_a_half_voxel_offset_cube_gives_its_boundary_voxels_half():
    """A cube whose faces cut its voxels in half: 2 samples per axis split them exactly."""
    vertices, triangles = cube(half=2.0)   # faces at +-2
    matrix = affine(np.eye(3), [-3.0, -3.0, -3.0])   # voxel centres at -3..3: faces cut voxels 1 and 5 in half
    fractions = inside_fraction(vertices, triangles, matrix, (7, 7, 7))
    assert fractions[3, 3, 3] == 1.0 and fractions[1, 3, 3] == 0.5 and fractions[1, 1, 3] == 0.25
    assert fractions[1, 1, 1] == 0.125 and fractions[0, 3, 3] == 0.0
    assert voxelised_volume(fractions, matrix) == pytest.approx(64.0)


def test_a_sphere_matches_its_volume_is_whole_inside_and_empty_far_outside():
    vertices, triangles = icosphere(4)   # 5120 triangles
    exact = mesh_volume(vertices, triangles)
    shape, matrix = fitted_grid(vertices.min(axis=0), vertices.max(axis=0), 48)
    fractions = inside_fraction(vertices, triangles, matrix, shape)
    assert voxelised_volume(fractions, matrix) == pytest.approx(exact, rel=SPHERE_TOLERANCE)
    assert fractions.min() == 0.0 and fractions.max() == 1.0
    centre = (np.array(shape) - 1) // 2
    assert fractions[tuple(centre)] == 1.0
    assert np.all(fractions[0] == 0) and np.all(fractions[:, :, -1] == 0)
    # Voxel centres within 0.9 of the centre are whole (their cells lie inside), beyond 1.1 empty.
    positions = np.indices(shape).reshape(3, -1).T @ matrix[:3, :3].T + matrix[:3, 3]
    distance = np.linalg.norm(positions, axis=1).reshape(shape)
    assert np.all(fractions[distance < 0.9] == 1.0)
    assert np.all(fractions[distance > 1.1] == 0.0)


def test_nested_shells_leave_the_hollow_empty():
    """Lines cross four surfaces: every crossing counts (multiple hits per line)."""
    outer, inner = icosphere(3, radius=1.0), icosphere(3, radius=0.5)
    vertices = np.vstack([outer[0], inner[0]])
    triangles = np.vstack([outer[1], inner[1] + len(outer[0])])
    exact = mesh_volume(*outer) - mesh_volume(*inner)
    shape, matrix = fitted_grid(vertices.min(axis=0), vertices.max(axis=0), 48)
    fractions = inside_fraction(vertices, triangles, matrix, shape)
    assert voxelised_volume(fractions, matrix) == pytest.approx(exact, rel=2 * SPHERE_TOLERANCE)
    assert fractions[tuple((np.array(shape) - 1) // 2)] == 0.0


def test_a_rotated_and_translated_grid_and_mesh_give_the_same_fractions():
    """Voxelising in object space then placing the grid equals voxelising the placed mesh
    with the placed grid (index_to_world carries any affine map)."""
    vertices, triangles = icosphere(3)
    shape, local = fitted_grid(vertices.min(axis=0), vertices.max(axis=0), 24)
    placement = affine(rotation([1, 2, 3], 0.7) @ np.diag([2.0, 0.5, 1.0]), [10.0, -4.0, 2.5])
    moved = vertices @ placement[:3, :3].T + placement[:3, 3]
    here = inside_fraction(vertices, triangles, local, shape)
    there = inside_fraction(moved, triangles, placement @ local, shape)
    np.testing.assert_array_equal(here, there)
    # And the placed volume is the mesh's volume times the placement's determinant.
    assert voxelised_volume(there, placement @ local) == pytest.approx(
        mesh_volume(moved, triangles), rel=2 * SPHERE_TOLERANCE)


def test_a_rotated_cube_in_an_axis_aligned_grid_matches_its_volume():
    vertices, triangles = cube(half=1.0)
    vertices = vertices @ rotation([1, 1, 0], 0.6).T + [0.2, 0.1, -0.3]
    shape, matrix = fitted_grid(vertices.min(axis=0), vertices.max(axis=0), 48)
    fractions = inside_fraction(vertices, triangles, matrix, shape)
    assert voxelised_volume(fractions, matrix) == pytest.approx(8.0, rel=SPHERE_TOLERANCE)
    centre = np.linalg.solve(matrix, [0.2, 0.1, -0.3, 1.0])[:3]
    assert fractions[tuple(np.round(centre).astype(int))] == 1.0


def test_the_winding_does_not_matter():
    vertices, triangles = icosphere(3)
    shape, matrix = fitted_grid(vertices.min(axis=0), vertices.max(axis=0), 24)
    mixed = triangles.copy()
    mixed[::3] = mixed[::3, ::-1]   # a third of the faces inside out
    np.testing.assert_array_equal(inside_fraction(vertices, triangles, matrix, shape),
                                  inside_fraction(vertices, mixed, matrix, shape))


def test_a_mesh_larger_than_the_grid_fills_it():
    vertices, triangles = cube(half=10.0)
    matrix = affine(np.eye(3) * 0.5, [-2.0, -2.0, -2.0])
    fractions = inside_fraction(vertices, triangles, matrix, (8, 8, 8))
    assert np.all(fractions == 1.0)


def test_a_grid_away_from_the_mesh_is_empty():
    vertices, triangles = icosphere(2)
    matrix = affine(np.eye(3) * 0.1, [5.0, 0.0, 0.0])
    assert not inside_fraction(vertices, triangles, matrix, (16, 16, 16)).any()


# ----------------------------------------------------------------------------- open and empty meshes

@pytest.mark.parametrize("missing", [["-z"], ["+x"], ["-z", "-x"]])
def test_an_open_cube_is_voxelised_as_if_closed(missing):
    """Lines through a missing face meet one face only (an odd count): they abstain, and the
    two other axes, which cross two faces, decide. With two adjacent faces missing, the
    samples near the open corner have two lines abstaining and the third still decides.
    (All three faces of one corner missing leaves nothing to decide with: not tested.)"""
    vertices, triangles = cube()
    shape, matrix = fitted_grid(vertices.min(axis=0), vertices.max(axis=0), 16)
    closed = inside_fraction(vertices, triangles, matrix, shape)
    drop = [i for face in missing for i in CUBE_FACE[face]]
    open_ = inside_fraction(vertices, np.delete(triangles, drop, axis=0), matrix, shape)
    np.testing.assert_array_equal(open_, closed)


def test_a_sphere_with_a_few_triangles_missing_keeps_its_volume():
    """Ten scattered holes: a sample goes wrong only where its lines' votes are misled, that
    is two of its three lines pass through holes (one abstains and another crosses two holes,
    or both abstain and the fallback guesses): a few samples of 260 k. A patch of 50 adjacent
    triangles (a hole about 0.4 wide) changes a few voxels near the hole only."""
    vertices, triangles = icosphere(4)
    shape, matrix = fitted_grid(vertices.min(axis=0), vertices.max(axis=0), 32)
    closed = inside_fraction(vertices, triangles, matrix, shape)
    scattered = inside_fraction(vertices, np.delete(triangles, np.arange(0, 5000, 500), axis=0), matrix, shape)
    wrong_samples = np.abs(scattered - closed).sum() * 8
    assert wrong_samples <= 8
    patch = inside_fraction(vertices, triangles[50:], matrix, shape)
    assert voxelised_volume(patch, matrix) == pytest.approx(voxelised_volume(closed, matrix), rel=0.002)
    assert (patch != closed).sum() < 0.01 * (closed > 0).sum()


def test_a_flat_mesh_has_no_inside():
    vertices = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], np.float64)
    triangles = np.array([[0, 1, 2], [0, 2, 3]])
    shape, matrix = fitted_grid(vertices.min(axis=0), vertices.max(axis=0), 16)
    assert not inside_fraction(vertices, triangles, matrix, shape).any()


def test_an_empty_mesh_gives_zeros():
    matrix = np.eye(4)
    for vertices, triangles in ((np.zeros((0, 3)), np.zeros((0, 3), np.int64)),
                                (np.zeros((3, 3)), np.zeros((0, 3), np.int32)),
                                (np.full((3, 3), np.nan), np.array([[0, 1, 2]]))):
        fractions = inside_fraction(vertices, triangles, matrix, (4, 5, 6))
        assert fractions.shape == (4, 5, 6) and fractions.dtype == np.float32 and not fractions.any()


def test_bad_arguments_are_refused():
    vertices, triangles = cube()
    with pytest.raises(ValueError):
        inside_fraction(vertices, triangles, np.eye(4), (4, 0, 4))
    with pytest.raises(ValueError):
        inside_fraction(vertices, triangles + 8, np.eye(4), (4, 4, 4))
    with pytest.raises(ValueError):
        inside_fraction(vertices, triangles, np.eye(4), (4, 4, 4), samples_per_axis=0)


def test_64_cubed_of_a_10k_triangle_mesh_casts_a_ray_per_crossing_not_per_sample(monkeypatch):
    """Measured ~0.2 s on 2 cores (64^3 voxels, 2^3 samples). Counted, not timed: the lines
    through the sample columns are traced layer by layer in batched calls, one ray per
    crossing and one more that leaves the mesh; a ray per sample (2 million here) or a call
    per triangle (10 000) would take minutes."""
    vertices, triangles = bumpy_sphere()
    assert len(triangles) == 10000
    shape, matrix = fitted_grid(vertices.min(axis=0), vertices.max(axis=0), 64)
    traced = []  # (rays, hits) of each embree call
    intersect_local = RayScene.intersect_local

    def counted(scene, origins, directions, *args, **kwargs):
        found = intersect_local(scene, origins, directions, *args, **kwargs)
        traced.append((len(origins), int(np.count_nonzero(found[0] >= 0))))
        return found

    monkeypatch.setattr(RayScene, "intersect_local", counted)
    fractions = inside_fraction(vertices, triangles, matrix, shape)
    s = 2  # inside_fraction's default samples_per_axis
    lines = sum(np.prod([n * s for a, n in enumerate(shape) if a != axis]) for axis in range(3))
    rays, hits = np.sum(traced, axis=0)
    # A line meets the bumpy sphere a few times (7 calls per axis measured): one call per layer.
    assert len(traced) <= 3 * 16
    assert rays - hits <= lines  # at most one ray per line finds nothing
    assert rays < fractions.size * s ** 3 / 4  # measured 122 000 rays for 2 million samples
    assert voxelised_volume(fractions, matrix) == pytest.approx(mesh_volume(vertices, triangles),
                                                                rel=SPHERE_TOLERANCE)


def test_a_side_a_float32_hair_over_whole_voxels_gets_that_many():
    """Blender's vertices are float32: a side of 4/9 read back is 4.0000001 voxels of 1/9."""
    thickness = float(np.float32(4.0 / 9.0))
    shape, _ = fitted_grid([-1.0, -1.0, -thickness / 2], [1.0, 1.0, thickness / 2], 20)
    assert shape == (20, 20, 6)
