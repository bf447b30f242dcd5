"""Where the samples are: texels of a UV atlas or vertices of a mesh, in world space.

``raster`` places texel centres in UV triangles, ``atlas`` checks a layout and unwraps
with xatlas (``unwrap_child`` runs that in a child process so it can be cancelled),
``layout`` decides which objects get atlases, vertex tables and how many texels, and
``samples`` turns either into positions, normals and materials per sample.
"""
