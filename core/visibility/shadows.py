"""Shadow fractions per sample and region (the paper's Figure 5) and their lookup."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import tolerances as tol
from .directions import ShadowRegions
from .table import BELOW_HORIZON, ENTRY_BYTES, MISS, RELEASE_BYTES, VisibilityTable, decode_distance


@dataclass
class ShadowFractions:
    """Per sample and region: traced directions and how many of them escaped.

    The fraction f_j = lit_j / traced_j; the lookup weights regions by a_j * traced_j,
    so a region whose directions all lie below the horizon takes no part instead of
    darkening grazing light as a fraction of zero would.

    lit : (K, M) uint16
    traced : (K, M) uint16
    """

    regions: ShadowRegions
    lit: np.ndarray
    traced: np.ndarray

    def fractions(self) -> np.ndarray:
        """f_j, (K, M) float32 (0 where a region was not traced)."""
        traced = self.traced.astype(np.float32)
        return np.divide(self.lit, traced, out=np.zeros_like(traced), where=traced > 0)

    def visibility(self, to_light: np.ndarray) -> np.ndarray:
        """V(p, l) in [0, 1] for one light direction per sample.

        Parameters
        ----------
        to_light : (K, 3) float64 unit vectors from each sample towards the light

        Returns
        -------
        visibility : (K,) float64
        """
        weights = np.clip(np.einsum("kd,md->km", to_light, self.regions.centres), 0.0, None) ** self.regions.exponent
        numerator = np.einsum("km,km->k", weights, self.lit.astype(np.float64))
        denominator = np.einsum("km,km->k", weights, self.traced.astype(np.float64))
        return np.divide(numerator, denominator, out=np.zeros_like(numerator), where=denominator > 0)


def shadow_fractions(table: VisibilityTable, regions: ShadowRegions, light_distance: np.ndarray | None = None,
                     rotations: np.ndarray | None = None, group: np.ndarray | None = None) -> ShadowFractions:
    """Count, per sample and region, the traced directions and the unoccluded ones.

    Parameters
    ----------
    light_distance : (K,) float or None
        Distance from each sample to a local light. Hits beyond it do not shadow
        that light. None (a distant light) counts only misses, as in the paper; a
        point light inside a closed room would otherwise be fully shadowed, since
        every direction from inside hits a wall somewhere.
    rotations : (G, 3, 3) and group : (K,) or None
        The table's interleaved rotations: sample k's direction i counts in the region of
        ``rotations[group[k]] @ d_i``.
    """
    from ..distributed.split import SplitTable

    if isinstance(table, SplitTable):
        return table.shadow_fractions(regions, light_distance)
    entries = table.entries
    samples = entries.samples
    lit = np.zeros((samples, regions.count), np.uint16)
    traced = np.zeros((samples, regions.count), np.uint16)
    limit = None
    if light_distance is not None:
        limit = (np.asarray(light_distance, np.float64) * (1.0 - tol.SHADOW_RAY_SHORTEN)).astype(np.float32)
    columns = np.arange(samples)
    # Rows read between handing the pages back (a table in a scratch file, TableEntries.release).
    release_rows = max(1, RELEASE_BYTES // max(ENTRY_BYTES * entries.stored // max(entries.directions, 1), 1))
    rotated = None
    if rotations is not None:
        turned = np.einsum("gab,nb->gna", rotations, np.asarray(table.directions, np.float64))
        rotated = np.argmax(turned @ regions.centres.T, axis=2).astype(np.int32)  # (G, N)
    for i, region in enumerate(regions.nearest):
        row = entries.dense("hit_object", i, i + 1)[0]
        if rotated is not None:
            region = (columns, rotated[group, i])  # one region per sample: no index repeats
        else:
            region = (slice(None), region)
        traced[region] += row != BELOW_HORIZON
        if limit is None:
            lit[region] += row == MISS
        else:
            distance = decode_distance(entries.dense("hit_distance_code", i, i + 1)[0])
            lit[region] += (row != BELOW_HORIZON) & (distance >= limit)
        if (i + 1) % release_rows == 0:
            entries.release()
    entries.release()
    return ShadowFractions(regions=regions, lit=lit, traced=traced)
