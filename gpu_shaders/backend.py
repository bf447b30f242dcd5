"""The GPU backend: the GLSL passes behind the transport contract
(:class:`core.transport.contract.TransportBackend`), within a GPU memory budget."""
from __future__ import annotations

import numpy as np

from ..core.outputs.dilation import dilate as numpy_dilate
from . import dilate as gpu_dilate
from . import direct as gpu_direct
from . import gather as gpu_gather
from . import passes as gpu_passes
from . import runtime


class GPUBackend:
    """Every transport pass on Blender's gpu module; ``budget_bytes`` bounds what one pass uploads."""

    name = "gpu"

    def __init__(self, budget_bytes: int):
        self.budget_bytes = int(budget_bytes)

    def lamp_irradiance(self, samples, shadowing, lights, report=None, spread: list | None = None
                        ) -> tuple[np.ndarray, int]:
        return gpu_direct.lamp_irradiance(samples, shadowing, lights, report, budget_bytes=self.budget_bytes,
                                          spread=spread)

    def gather(self, geometry, source, progress=None, samples: np.ndarray | None = None,
               directions: range | None = None) -> np.ndarray:
        return gpu_gather.gather(geometry, source, progress, samples, directions, budget_bytes=self.budget_bytes)

    def accumulate_passes(self, albedo: np.ndarray, wants, groups: dict, per_group: bool) -> dict:
        return gpu_passes.accumulate_passes(albedo, wants, groups, per_group)

    def dilate(self, image: np.ndarray, coverage: np.ndarray, margin: int) -> tuple[np.ndarray, np.ndarray]:
        """The GPU dilation; numpy for images beyond the GPU's texture size or memory budget."""
        if max(np.shape(coverage)) > runtime.MAX_TEXTURE_SIZE:
            return numpy_dilate(image, coverage, margin)
        try:
            return gpu_dilate.dilate(image, coverage, margin, budget_bytes=self.budget_bytes)
        except MemoryError:
            return numpy_dilate(image, coverage, margin)
