"""GLSL compute passes on Blender's gpu module, each the twin of a numpy pass in core/.

``runtime`` makes a context (also in background mode), chooses the device and
compiles the ``.glsl`` sources beside it lazily; ``gather`` is the bounce gather.
Nothing here runs at import or register time.
"""
from . import backend, dilate, direct, gather, passes, runtime, volume_sweep  # noqa: F401
