"""The Blender side of the data flow, used by the operators and the command line.

``extract`` reads meshes, materials, lamps and the world into core arrays; ``layout``
chooses and writes UV maps; ``refine`` makes subdivided copies of coarse vertex-mode
objects; ``job`` runs a bake in steps (plan, unwrap, extract, compute, finish) and
undoes what it created on failure; ``writeback`` writes images, colour attributes and
files; ``device`` chooses the transport backend; ``cache_status`` tracks whether the
cached table is still valid; ``preview_nodes`` and ``preview_render`` show the
results; ``demo_scene`` builds the demo; ``settings`` turns arguments, the scene's
properties and the preferences into a bake's core settings.
"""

# The extension's own package (``bl_ext.<repository>.visibake``), never hard-coded.
EXTENSION_PACKAGE = __package__.rpartition(".")[0].rpartition(".")[0]
