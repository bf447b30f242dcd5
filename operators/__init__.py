"""What the user runs: the operators (Bake, Relight, the preview buttons, Clear Cache, Bake Volume)
and the headless command (``cli``). They stay thin: the Blender side of the data flow
is in ``adapter``, everything else in ``core``."""
from ..panels import properties
from . import appearance, bake, cache, preview, volume

classes = properties.classes + bake.classes + cache.classes + preview.classes + volume.classes + appearance.classes
