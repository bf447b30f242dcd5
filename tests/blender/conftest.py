"""Fixtures for tests that run inside bpy with the extension installed.

``visibake`` (session): the installed, enabled module ``bl_ext.user_default.visibake``.
``clean_scene`` (function): empty factory scene, extension re-enabled.
See tests/blender_support.py; tests/gpu/conftest.py can re-export the same way.
"""

from blender_support import clean_scene, visibake  # noqa: F401
