"""The CPU backend: the passes of :mod:`core.transport` (table lookups in the compiled
kernels of :mod:`core.kernels`, or in numpy where those cannot load), behind the transport
contract. It is the twin every GPU pass is tested against."""
from __future__ import annotations

import numpy as np

from ..outputs.dilation import dilate
from .contract import GatherGeometry, GatherSource, SampleSet, Shadowing
from .direct import lamp_irradiance
from .gather import gather
from .passes import accumulate_passes


class NumpyBackend:
    """:class:`core.transport.contract.TransportBackend` on the CPU: compiled lookups, numpy
    and embree (shadow rays)."""

    name = "cpu"

    def lamp_irradiance(self, samples: SampleSet, shadowing: Shadowing, lights, report=None,
                        spread: list | None = None) -> tuple[np.ndarray, int]:
        return lamp_irradiance(samples, shadowing, lights, report, spread)

    def gather(self, geometry: GatherGeometry, source: GatherSource, progress=None,
               samples: np.ndarray | None = None, directions: range | None = None) -> np.ndarray:
        return gather(geometry, source, progress, samples, directions)

    def accumulate_passes(self, albedo: np.ndarray, wants, groups: dict, per_group: bool) -> dict:
        return accumulate_passes(albedo, wants, groups, per_group)

    def dilate(self, image: np.ndarray, coverage: np.ndarray, margin: int) -> tuple[np.ndarray, np.ndarray]:
        return dilate(image, coverage, margin)


CPU_BACKEND = NumpyBackend()
