"""Scale-out: what crosses from the machine that prepares a bake to workers without Blender."""
