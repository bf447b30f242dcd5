"""The bake as stages: ``budget`` (memory), ``progress`` (stage timing and time left),
``prepare`` (samples and the visibility table, from geometry alone) and ``relight``
(lights -> transport -> pass images, as often as the lights change)."""
