"""GLSL compute passes on Blender's gpu module (see issue: transport passes on the gpu module).

Nothing here yet: every transport pass currently runs in numpy (core.transport),
which DESIGN.md measured as the faster path on machines without a real GPU.
"""
