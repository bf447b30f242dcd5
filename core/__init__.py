"""VisiBake core: precomputed-visibility light transport in numpy + embreex.

Nothing in this package imports Blender; the operators adapt Blender data to the
plain arrays and dataclasses defined in :mod:`core.scene`.
"""
