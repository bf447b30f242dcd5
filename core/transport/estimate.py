"""The bake's estimate of its own error, from the independent estimates it already makes.

Two parts of a bake's light are sums of samples whose scatter it can see:

- **Direct light over a texel's footprint.** Where a shadow edge or a penumbra crosses a
  texel, every point of its footprint (and of the lamp) is traced, and the points are a
  scrambled Sobol set whose first and second halves are each stratified: two estimates of
  the same light. Half their difference is the whole set's standard error (an overestimate
  by about 2^(1/4) for a step, since complementary halves of a net are negatively
  correlated); texels the probes decided wholly lit or shadowed have none
  (core.transport.direct).
- **Gathered light over the direction set.** Neighbouring texels use other rotations of the
  set (core.transport.interleave), so the far radiance of a window's texels scatters by the
  fixed set's error; the filter averages them, and their scatter over the square root of
  their count is the average's standard error. Where the far light itself changes across the
  window the scatter includes that change, an overestimate.

What neither sees is bias: light the method gets wrong the same way in every sample
(a penumbra the probes misjudged, light leaking through thin walls, the filter's blur, the
near light kept unfiltered, directly sampled emitters). The estimate is therefore a lower
bound wherever such bias dominates; benchmarks/error_calibration.py measures it against
Cycles on scenes built inside and outside the project.

The figures are those of the benchmarks' per-texel metric (benchmarks/reference.py
relative_errors): the RMS over texels and colour channels of the lighting pass's standard
error, over the mean lighting value.
"""
from __future__ import annotations

import numpy as np


def lighting_error(albedo: np.ndarray, parts: dict, sample_offset: np.ndarray, objects: np.ndarray) -> dict | None:
    """The estimated relative RMS error of the lighting pass, in total and per object.

    Parameters
    ----------
    albedo : (K, 3) float64 per-sample albedo
    parts : light group name -> core.transport.groups.Transported (its ``direct_variance`` and
        ``gathered_variance`` (K, 3) float64, NaN where unknown)
    sample_offset : (objects + 1,) int64, first sample of each object
    objects : indices of the objects the estimate covers (the outputs)

    Returns None when a part has no estimate at all (read back from a cache); else a dict:
    ``total``, ``lamps`` (the lamps' direct light) and ``gathered`` (all light through the table:
    the world's, the emitters' and the bounces'), relative RMS over the objects' samples (None
    where no sample has an estimate), ``unestimated_share`` (of the samples, those without one)
    and ``objects`` {index: {total, lamps, gathered}}. Light groups' errors add as independent.
    """
    if not parts or any(t.direct_variance is None or t.gathered_variance is None for t in parts.values()):
        return None
    light = sum(t.direct + t.gathered for t in parts.values())
    direct_variance = sum(t.direct_variance for t in parts.values())
    gathered_variance = sum(t.gathered_variance for t in parts.values())
    # The lighting pass is albedo / pi times the irradiance: so are its errors.
    scale = np.square(albedo / np.pi)
    value = albedo / np.pi * light
    lamps = scale * direct_variance
    gathered = scale * gathered_variance
    rows = np.concatenate([np.arange(sample_offset[i], sample_offset[i + 1]) for i in objects]) if len(objects) \
        else np.zeros(0, np.int64)
    result = _relative(value[rows], lamps[rows], gathered[rows])
    result["objects"] = {int(i): _relative(value[a:b], lamps[a:b], gathered[a:b])
                         for i in objects for a, b in [(sample_offset[i], sample_offset[i + 1])]}
    for entry in result["objects"].values():
        entry.pop("unestimated_share")
    return result


def _relative(value: np.ndarray, lamps: np.ndarray, gathered: np.ndarray) -> dict:
    """Relative RMS errors of samples with lighting ``value`` (k, 3) and squared standard errors
    ``lamps`` and ``gathered`` (k, 3), over the samples where both are known."""
    known = np.isfinite(lamps).all(axis=1) & np.isfinite(gathered).all(axis=1)
    mean = float(np.mean(value)) if len(value) else 0.0
    if not known.any() or not mean > 0:
        return {"total": None, "lamps": None, "gathered": None,
                "unestimated_share": float(1.0 - known.mean()) if len(known) else 1.0}

    def rms(variance):
        return float(np.sqrt(np.mean(variance[known])) / mean)

    return {"total": rms(lamps + gathered), "lamps": rms(lamps), "gathered": rms(gathered),
            "unestimated_share": float(1.0 - known.mean())}
