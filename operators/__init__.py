"""What the user runs: the operators (Bake, Relight, the preview buttons, Clear Cache, Bake Volume,
Simulate BRDF and BTF, Render Light Field) and the headless command (``cli``). They stay thin:
the Blender side of the data flow is in ``adapter``, everything else in ``core``."""
from ..panels import properties
from . import appearance, bake, cache, lightfield, preview, volume

classes = (properties.classes + bake.classes + cache.classes + preview.classes + volume.classes + appearance.classes
           + lightfield.classes)
