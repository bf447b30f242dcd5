"""Vertex-mode result files (core.outputs.vertex_files): the PLY layout, both domains, and
that nothing non-finite is ever written."""
import numpy as np
import pytest

from core.errors import OutputRefused
from core.outputs.vertex_files import element_geometry, read_ply, write_ply

# Two triangles over a unit square; four vertices, six face corners (loops).
POSITIONS = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]])
TRIANGLES = np.array([[0, 1, 2], [0, 2, 3]])
LOOPS = np.array([[0, 1, 2], [3, 4, 5]])


def test_point_results_keep_the_mesh_vertices():
    positions, faces = element_geometry(POSITIONS, TRIANGLES, LOOPS, "POINT")
    np.testing.assert_array_equal(positions, POSITIONS)
    np.testing.assert_array_equal(faces, TRIANGLES)


def test_corner_results_get_one_vertex_per_corner_at_its_vertex():
    positions, faces = element_geometry(POSITIONS, TRIANGLES, LOOPS, "CORNER", loop_count=6)
    assert positions.shape == (6, 3)
    np.testing.assert_array_equal(faces, LOOPS)
    # Each face's corners sit where its triangle's vertices are.
    np.testing.assert_array_equal(positions[faces], POSITIONS[TRIANGLES])
    with pytest.raises(ValueError):
        element_geometry(POSITIONS, TRIANGLES, None, "CORNER", 6)
    with pytest.raises(ValueError):
        element_geometry(POSITIONS, TRIANGLES, LOOPS, "FACE")


def test_round_trip_is_exact(tmp_path):
    rng = np.random.default_rng(3)
    colors = np.concatenate([rng.random((4, 3)) * 50.0, np.ones((4, 1))], axis=1).astype(np.float32)
    far = POSITIONS + 1e5 + 0.001  # float32 would lose the millimetre here
    path = tmp_path / "lighting.ply"
    write_ply(str(path), far, TRIANGLES, colors, comment="test\nsecond line")
    positions, faces, read = read_ply(str(path))
    np.testing.assert_array_equal(positions, far)
    np.testing.assert_array_equal(faces, TRIANGLES)
    np.testing.assert_array_equal(read, colors[:, :3])
    header = path.read_bytes().split(b"end_header\n")[0].decode()
    assert "format binary_little_endian 1.0" in header and "property float red" in header
    assert "comment test" in header and "comment second line" in header


def test_preview_is_eight_bit(tmp_path):
    path = tmp_path / "lighting.preview.ply"
    write_ply(str(path), POSITIONS, TRIANGLES, np.array([[0.0, 0.5, 1.0]] * 4), display=True)
    _, _, read = read_ply(str(path))
    np.testing.assert_array_equal(read, [[0, 128, 255]] * 4)
    assert b"property uchar red" in path.read_bytes()


def test_non_finite_colours_are_refused_and_non_finite_positions_never_written(tmp_path):
    path = tmp_path / "bad.ply"
    with pytest.raises(OutputRefused, match="non-finite"):
        write_ply(str(path), POSITIONS, TRIANGLES, np.array([[np.nan, 0.0, 0.0]] + [[0.0, 0.0, 0.0]] * 3))
    assert not path.exists()
    positions = POSITIONS.copy()
    positions[3] = np.inf  # a user's broken vertex: only the second triangle uses it
    write_ply(str(path), positions, TRIANGLES, np.zeros((4, 3)))
    read_positions, faces, _ = read_ply(str(path))
    assert np.all(np.isfinite(read_positions))
    np.testing.assert_array_equal(faces, TRIANGLES[:1])
