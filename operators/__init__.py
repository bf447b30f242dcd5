"""Blender operators and the Blender side of the data flow (extraction, write-back)."""
from . import bake
from .adapter import cache_status, preview_nodes
from ..panels import properties

classes = properties.classes + bake.classes + cache_status.classes + preview_nodes.classes
