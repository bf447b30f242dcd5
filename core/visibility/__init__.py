"""What every sample sees: the paper's precomputed visibility.

``directions`` is the global direction set D (and the shadow regions c_j), ``rays``
traces through embree, ``table`` is the scattering table S_i (per sample and direction:
what the ray hits), ``shadows`` reduces it to shadow fractions, and ``cache`` keeps
tables on disk, keyed by geometry and settings, for relighting.
"""
