"""Direct light from lamps: unshadowed irradiance per virtual point, then shadows
from the paper's shadow fractions or from exact shadow rays."""
from __future__ import annotations

import numpy as np

from .. import tolerances as tol
from ..lights.lamps import light_contributions
from .contract import SampleSet, Shadowing


def lamp_irradiance(samples: SampleSet, shadowing: Shadowing, lights, report=None) -> tuple[np.ndarray, int]:
    """(K, 3) float64 irradiance of ``lights`` at ``samples``, and the shadow rays traced.

    Shadows as ``shadowing`` says (exact rays, or the paper's fractions);
    ``report(fraction)`` is called after each lamp. The CPU backend's direct-light pass.
    """
    fractions_mode = bool(lights) and shadowing.mode == "fractions"
    irradiance = np.zeros((len(samples.position), 3))
    shadow_rays = 0
    # Progress by shadow rays, not by lamps: an area lamp traces several per sample.
    costs = np.cumsum([shadow_rays_per_sample(light.kind, shadowing) for light in lights])
    for light_index, light in enumerate(lights):
        fractions = None
        if fractions_mode:
            if light.kind == "SUN":
                fractions = shadowing.distant_fractions()
            else:
                light_distance = np.linalg.norm(samples.position - np.asarray(light.position, np.float64), axis=1)
                fractions = shadowing.local_fractions(light_distance)
        for part in light_contributions(light, samples.position, samples.normal, shadowing.area_light_samples):
            above = np.einsum("kd,kd->k", part.to_light, samples.geometric) > 0.0
            lit = above & np.any(part.irradiance > 0, axis=1)
            if fractions is not None:
                visibility = np.where(lit, fractions.visibility(part.to_light), 0.0)
            else:
                visibility = lit.astype(np.float64)
                rays = np.nonzero(lit)[0]
                if len(rays):
                    distance = part.distance[rays]
                    limit = np.where(np.isfinite(distance), distance * (1.0 - tol.SHADOW_RAY_SHORTEN), np.inf)
                    blocked = shadowing.ray_scene.occluded(samples.origins[rays], part.to_light[rays],
                                                           limit.astype(np.float32))
                    visibility[rays[blocked]] = 0.0
                    shadow_rays += len(rays)
            irradiance += part.irradiance * visibility[:, None]
        if report is not None:
            report(costs[light_index] / costs[-1])
    return irradiance, shadow_rays


# An exact shadow ray costs about as much as this many table lookups of a gather
# (embree ~5 M rays/s, the numpy gather ~15 M lookups/s on 2 cores).
SHADOW_RAY_IN_LOOKUPS = 3.0


def shadow_rays_per_sample(kind: str, settings) -> int:
    """Shadow rays a lamp of this kind traces per sample with exact shadows (``settings``:
    anything with ``area_light_samples``, such as BakeSettings or a Shadowing)."""
    return settings.area_light_samples if kind == "AREA" else 1
