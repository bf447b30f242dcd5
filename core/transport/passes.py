"""Pass values from transported irradiance: ``lighting`` (rho E / pi, Cycles' DIFFUSE
bake with colour), ``direct``, ``indirect`` and ``irradiance`` (E / pi), summed over
light groups and, on request, per group."""
from __future__ import annotations

import numpy as np


def lighting_passes(albedo: np.ndarray, wants, direct: np.ndarray, gathered: np.ndarray) -> dict:
    """Per-sample values (K, 3) of the requested lighting passes, from E_direct and E_gathered."""
    per_pass = {}
    if "lighting" in wants:
        per_pass["lighting"] = albedo / np.pi * (direct + gathered)
    if "direct" in wants:
        per_pass["direct"] = albedo / np.pi * direct
    if "indirect" in wants:
        per_pass["indirect"] = albedo / np.pi * gathered
    if "irradiance" in wants:
        per_pass["irradiance"] = (direct + gathered) / np.pi
    return per_pass


def accumulate_passes(albedo: np.ndarray, wants, groups: dict, per_group: bool) -> dict:
    """The lighting passes of one lighting: the sum over its groups and, with ``per_group``, each group's.

    Parameters
    ----------
    albedo : (K, 3) float64
    wants : the requested pass names
    groups : group name -> Transported (direct and gathered irradiance, (K, 3) each)

    Returns
    -------
    pass name (``lighting``, or ``lighting_<group>`` per group) -> (K, 3) float64
    """
    if not groups:
        return {}
    direct = sum(t.direct for t in groups.values())
    gathered = sum(t.gathered for t in groups.values())
    per_pass = lighting_passes(albedo, wants, direct, gathered)
    if per_group:
        for name, t in groups.items():
            for pass_name, values in lighting_passes(albedo, wants, t.direct, t.gathered).items():
                per_pass[group_pass_name(pass_name, name)] = values
    return per_pass


def group_pass_name(pass_name: str, group: str) -> str:
    """Name of a pass of one light group, e.g. ``lighting_Sun``."""
    return f"{pass_name}_{group}"
