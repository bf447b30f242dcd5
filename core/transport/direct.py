"""Direct light from lamps: unshadowed irradiance per virtual point, then shadows
from the paper's shadow fractions or from exact shadow rays."""
from __future__ import annotations

import numpy as np

from .. import tolerances as tol
from ..lights.lamps import light_contributions
from ..visibility.shadows import shadow_fractions


def lamp_irradiance(p, lights, report) -> tuple[np.ndarray, int]:
    """(K, 3) irradiance of ``lights`` with shadows as the settings say, and shadow rays traced.

    ``p`` is a prepared scene (positions, normals, geometric normals, ray origins, the
    table and settings); ``report(fraction)`` is called after each lamp. The direct-light
    pass; ``p.lamp_irradiance`` may be a twin with the same contract on another device.
    """
    settings = p.settings
    regions = p.shadow_regions() if lights and settings.shadows == "fractions" else None
    irradiance = np.zeros((len(p.position), 3))
    shadow_rays = 0
    # Progress by shadow rays, not by lamps: an area lamp traces several per sample.
    costs = np.cumsum([shadow_rays_per_sample(light.kind, settings) for light in lights])
    for light_index, light in enumerate(lights):
        fractions = None
        if regions is not None:
            if light.kind == "SUN":
                fractions = p.distant_fractions()
            else:
                light_distance = np.linalg.norm(p.position - np.asarray(light.position, np.float64), axis=1)
                fractions = shadow_fractions(p.table, regions, light_distance)
        for part in light_contributions(light, p.position, p.normal, settings.area_light_samples):
            above = np.einsum("kd,kd->k", part.to_light, p.geometric) > 0.0
            lit = above & np.any(part.irradiance > 0, axis=1)
            if fractions is not None:
                visibility = np.where(lit, fractions.visibility(part.to_light), 0.0)
            else:
                visibility = lit.astype(np.float64)
                rays = np.nonzero(lit)[0]
                if len(rays):
                    distance = part.distance[rays]
                    limit = np.where(np.isfinite(distance), distance * (1.0 - tol.SHADOW_RAY_SHORTEN), np.inf)
                    blocked = p.ray_scene.occluded(p.origins[rays], part.to_light[rays], limit.astype(np.float32))
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
    """Shadow rays a lamp of this kind traces per sample with exact shadows."""
    return settings.area_light_samples if kind == "AREA" else 1
