"""Where the transport passes run: the preference (or --device) turned into a gather.

``auto`` runs the GPU passes on a real GPU and numpy on a software renderer (Mesa
llvmpipe) or where no GPU context can be made; ``gpu`` and ``cpu`` force one.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass

import bpy
import numpy as np

from ...core.transport.passes import accumulate_passes as numpy_accumulate_passes
from ...core.transport.direct import lamp_irradiance as numpy_lamp_irradiance
from ...core.outputs.dilation import dilate as numpy_dilate
from ...core.transport.gather import gather as numpy_gather
from ...gpu_shaders import dilate as gpu_dilate
from ...gpu_shaders import direct as gpu_direct
from ...gpu_shaders import gather as gpu_gather
from ...gpu_shaders import passes as gpu_passes
from ...gpu_shaders import runtime
from . import EXTENSION_PACKAGE

DEVICES = ("auto", "gpu", "cpu")
ADDON_PACKAGE = EXTENSION_PACKAGE
DEFAULT_GPU_MEMORY_MIB = 1024


def preferences(context=None):
    """VisiBake's add-on preferences, or None where it is not an enabled add-on."""
    context = context or bpy.context
    addon = context.preferences.addons.get(ADDON_PACKAGE)
    return addon.preferences if addon is not None else None


class DeviceError(ValueError):
    """The requested device cannot be used; the message says why and what to do."""


@dataclass
class DeviceChoice:
    """The passes one bake runs, and what the report says about the device."""

    name: str  # 'gpu' or 'cpu'
    report: dict
    gather: object = numpy_gather
    accumulate_passes: object = numpy_accumulate_passes
    lamp_irradiance: object = numpy_lamp_irradiance
    dilate: object = numpy_dilate

    def apply(self, prepared) -> None:
        """Make ``prepared`` (core.pipeline.prepare.Prepared) run its passes on this device."""
        prepared.gather = self.gather
        prepared.gather_device = self.name
        prepared.accumulate_passes = self.accumulate_passes
        prepared.accumulate_device = self.name
        prepared.lamp_irradiance = self.lamp_irradiance
        prepared.direct_device = self.name
        prepared.dilate = self.dilate
        prepared.dilate_device = self.name


def choose(context=None, requested: str | None = None) -> DeviceChoice:
    """The device for ``requested`` ('auto', 'gpu', 'cpu'; None: the preference)."""
    prefs = preferences(context)
    requested = requested or (prefs.device if prefs is not None else "auto")
    if requested not in DEVICES:
        raise DeviceError(f"device must be one of {', '.join(DEVICES)}, got {requested!r}")
    try:
        used, reason, info = runtime.choose_device(requested)
    except runtime.GPUUnavailable as error:
        raise DeviceError(f"device gpu: {error}; use device cpu or auto") from None
    report = {"requested": requested, "used": used, "reason": reason}
    if info is not None:
        report.update(info.as_dict())
    if used == "cpu":
        return DeviceChoice("cpu", report)
    budget_mib = prefs.gpu_memory_mib if prefs is not None else DEFAULT_GPU_MEMORY_MIB
    report["gpu_memory_budget_mib"] = budget_mib
    budget = int(budget_mib) << 20
    return DeviceChoice("gpu", report, gather=functools.partial(gpu_gather.gather, budget_bytes=budget),
                        accumulate_passes=gpu_passes.accumulate_passes,
                        lamp_irradiance=functools.partial(gpu_direct.lamp_irradiance, budget_bytes=budget),
                        dilate=functools.partial(_dilate_on_gpu, budget_bytes=budget))


def _dilate_on_gpu(image, coverage, margin, budget_bytes):
    """The GPU dilation; numpy for images beyond the GPU's texture size or memory budget."""
    if max(np.shape(coverage)) > runtime.MAX_TEXTURE_SIZE:
        return numpy_dilate(image, coverage, margin)
    try:
        return gpu_dilate.dilate(image, coverage, margin, budget_bytes=budget_bytes)
    except MemoryError:
        return numpy_dilate(image, coverage, margin)
