"""Appearance from micro-geometry: BRDF/BSDF tables and BTFs (the paper's sections 7.1 and 7.2)."""
