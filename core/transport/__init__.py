"""Light transport by table lookups (the Method of Dependent Tests).

``contract`` defines what a transport backend is: the sample set it works on and the
passes it implements (gather, direct light, pass accumulation, dilation). The numpy
passes here are the CPU backend; ``gpu_shaders`` holds a GLSL backend with the same
contract. ``gather`` is the bounce gather, ``direct`` the lamps' direct light,
``groups`` carries light groups through both, ``passes`` turns irradiance into the
output passes.
"""
