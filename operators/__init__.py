"""Blender operators and the Blender side of the data flow (extraction, write-back)."""
from . import bake, properties

classes = properties.classes + bake.classes
