"""Vertex-mode results as files: one binary little-endian PLY per pass.

A vertex-mode object's result lives on its mesh (a colour attribute), which a bake with
``--out`` and no ``--save`` would lose; so it is also written as a mesh file any tool
can read. The format (the README's *Outputs* says the same):

- ``element vertex``: ``double x, y, z`` world-space positions (double: far from the
  origin float32 would move them), ``float red, green, blue`` linear radiance in Cycles'
  units (exactly the values of the ``VB_<pass>`` attribute; not clamped, not encoded).
- ``element face``: ``list uchar int vertex_indices``, the mesh's triangles, counter-clockwise
  seen from the front.

A result on the point domain has one PLY vertex per mesh vertex, in the mesh's order. A
result on the face-corner domain (split normals give a vertex's corners different light)
has one PLY vertex per face corner, in the mesh's corner order, at its vertex's position:
the triangles then use the corners, so every corner keeps its own colour and any reader
shows them (welding them would average the light across a sharp edge). Elements no valid
triangle uses are black. Blender reads the files back with
``bpy.ops.wm.ply_import(filepath=..., import_colors='LINEAR')`` (its default, sRGB, would
decode the values once more).

The preview variant (``--previews``) stores tone-mapped display colours as ``uchar``, the
colour type every mesh viewer shows.
"""
from __future__ import annotations

import os

import numpy as np

from ..errors import OutputRefused

_FACE_DTYPE = np.dtype([("count", "u1"), ("indices", "<i4", (3,))])


def element_geometry(positions: np.ndarray, triangles: np.ndarray, corner_loops: np.ndarray | None, domain: str,
                     loop_count: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The PLY vertices and faces of a result on ``domain``.

    Parameters
    ----------
    positions : (n, 3) float world-space vertex positions
    triangles : (m, 3) int vertex indices per triangle
    corner_loops : (m, 3) int the face corner (loop) of each triangle corner, in the same
        order as ``triangles``; needed for domain 'CORNER'
    domain : 'POINT' or 'CORNER', as the result's colours
    loop_count : number of face corners of the mesh (domain 'CORNER')

    Returns
    -------
    element_positions : (n or loop_count, 3) float64, one per element of the domain
    faces : (m, 3) int32 indices into ``element_positions``
    """
    positions = np.asarray(positions, np.float64).reshape(-1, 3)
    triangles = np.asarray(triangles, np.int64).reshape(-1, 3)
    if domain == "POINT":
        return positions, triangles.astype(np.int32)
    if domain != "CORNER":
        raise ValueError(f"domain must be 'POINT' or 'CORNER', got {domain!r}")
    if corner_loops is None:
        raise ValueError("a face-corner result needs the corners of its triangles")
    corner_loops = np.asarray(corner_loops, np.int64).reshape(-1, 3)
    corner_vertex = np.zeros(max(int(loop_count), int(corner_loops.max(initial=-1)) + 1), np.int64)
    corner_vertex[corner_loops.ravel()] = triangles.ravel()
    return positions[corner_vertex], corner_loops.astype(np.int32)


def write_ply(path: str, positions: np.ndarray, faces: np.ndarray, colors: np.ndarray, display: bool = False,
              comment: str = "") -> None:
    """Write a binary little-endian PLY of a coloured triangle mesh.

    Parameters
    ----------
    positions : (k, 3) float, written as double
    faces : (m, 3) int indices into ``positions``
    colors : (k, 3 or 4) float; alpha is not written. Linear values are written as float32;
        with ``display``, values in [0, 1] (display-encoded) are written as uchar
    comment : one line for the header (who wrote it, what the values are)

    Raises :class:`OutputRefused` rather than write a non-finite colour. Vertices with a
    non-finite position (the user's mesh can hold them) are written at the origin and
    the faces that use them are left out, so the file holds only finite numbers.
    """
    positions = np.asarray(positions, np.float64).reshape(-1, 3)
    faces = np.asarray(faces, np.int64).reshape(-1, 3)
    rgb = np.asarray(colors, np.float32)[:, :3]
    if len(rgb) != len(positions):
        raise ValueError(f"{len(rgb)} colours for {len(positions)} vertices")
    if not np.all(np.isfinite(rgb)):
        raise OutputRefused(f"refusing to write non-finite values to {path}")
    finite = np.all(np.isfinite(positions), axis=1)
    positions = np.where(finite[:, None], positions, 0.0)
    faces = faces[np.all(finite[faces], axis=1)] if len(faces) else faces
    color_type = "uchar" if display else "float"
    color_dtype = "u1" if display else "<f4"
    vertex_dtype = np.dtype([("position", "<f8", (3,)), ("color", color_dtype, (3,))])
    vertices = np.empty(len(positions), vertex_dtype)
    vertices["position"] = positions
    vertices["color"] = np.round(np.clip(rgb, 0.0, 1.0) * 255.0) if display else rgb
    face_records = np.empty(len(faces), _FACE_DTYPE)
    face_records["count"] = 3
    face_records["indices"] = faces
    header = ["ply", "format binary_little_endian 1.0"]
    header += [f"comment {line}" for line in comment.splitlines() if line.strip()]
    header += [f"element vertex {len(vertices)}", "property double x", "property double y", "property double z",
               f"property {color_type} red", f"property {color_type} green", f"property {color_type} blue",
               f"element face {len(face_records)}", "property list uchar int vertex_indices", "end_header"]
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with open(path, "wb") as handle:
        handle.write(("\n".join(header) + "\n").encode("ascii", "replace"))
        handle.write(vertices.tobytes())
        handle.write(face_records.tobytes())


def read_ply(path: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read back a file :func:`write_ply` wrote: (positions (k, 3) float64, faces (m, 3) int32,
    colors (k, 3) float32, as stored: linear floats, or uchar 0..255 of a preview).

    Raises ValueError for any other layout.
    """
    with open(path, "rb") as handle:
        data = handle.read()
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply\n") or end < 0:
        raise ValueError(f"{path} is not a PLY file")
    lines = [line for line in data[:end].decode("ascii").splitlines() if not line.startswith("comment")]
    if "format binary_little_endian 1.0" not in lines:
        raise ValueError(f"{path} is not binary little-endian")
    counts = {line.split()[1]: int(line.split()[2]) for line in lines if line.startswith("element ")}
    color_type = next((line.split()[1] for line in lines if line.endswith(" red")), "float")
    vertex_dtype = np.dtype([("position", "<f8", (3,)), ("color", "u1" if color_type == "uchar" else "<f4", (3,))])
    body = data[end + len(b"end_header\n"):]
    vertex_bytes = counts["vertex"] * vertex_dtype.itemsize
    if len(body) != vertex_bytes + counts["face"] * _FACE_DTYPE.itemsize:
        raise ValueError(f"{path}: body size does not match its header")
    vertices = np.frombuffer(body[:vertex_bytes], vertex_dtype)
    faces = np.frombuffer(body[vertex_bytes:], _FACE_DTYPE)
    if np.any(faces["count"] != 3):
        raise ValueError(f"{path}: only triangles are supported")
    return (vertices["position"].astype(np.float64), faces["indices"].astype(np.int32),
            vertices["color"].astype(np.float32))
