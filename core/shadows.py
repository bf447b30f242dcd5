"""Shadow fractions per sample and region (the paper's Figure 5) and their lookup."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .directions import ShadowRegions
from .visibility import BELOW_HORIZON, MISS, VisibilityTable


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


def shadow_fractions(table: VisibilityTable, regions: ShadowRegions) -> ShadowFractions:
    """Count, per sample and region, the traced directions and the misses among them."""
    samples = table.hit_object.shape[1]
    lit = np.zeros((samples, regions.count), np.uint16)
    traced = np.zeros((samples, regions.count), np.uint16)
    for i, region in enumerate(regions.nearest):
        row = table.hit_object[i]
        traced[:, region] += row != BELOW_HORIZON
        lit[:, region] += row == MISS
    return ShadowFractions(regions=regions, lit=lit, traced=traced)
