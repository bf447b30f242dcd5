"""VisiBake core: precomputed-visibility light transport in numpy + embreex + xatlas.

Nothing in this package imports Blender (tests/core/test_layering.py checks it); the
Blender side (``operators/adapter``) fills the plain dataclasses of :mod:`core.scene`.
The subpackages are the stages of a bake, in the order the data flows:

    scene, settings --sampling--> samples (texels or vertices, world space)
        --visibility--> the table S_i: what each sample sees in each direction (+ cache)
        --lights--> lamps, emitters, world, lighting setups in Cycles' units
        --transport--> direct light and gathers by table lookups, on a backend
        --outputs--> pass images, dilation, the report

``pipeline`` runs them (``prepare``: everything that depends on geometry alone;
``relight``: everything that depends on the lights). ``errors`` holds the exceptions
that mean "the user's input" (exit 2) as opposed to a bug (exit 1), ``geometry`` the
triangle maths every stage shares, ``tolerances`` every epsilon (part of the cache key).
"""
