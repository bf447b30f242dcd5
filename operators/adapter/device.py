"""Where the transport passes run: the preference (or --device) turned into a transport backend.

``auto`` runs the GPU passes on a real GPU and the CPU passes on a software renderer (Mesa
llvmpipe) or where no GPU context can be made; ``gpu`` and ``cpu`` force one.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import bpy

from ...core.errors import DeviceError
from ...core.settings import DEVICES, PREFERENCE_SETTINGS
from ...core.transport.contract import TransportBackend
from ...core.transport.cpu import CPU_BACKEND
from ...gpu_shaders import runtime
from ...gpu_shaders.backend import GPUBackend
from . import EXTENSION_PACKAGE

ADDON_PACKAGE = EXTENSION_PACKAGE


def preferences(context=None):
    """VisiBake's add-on preferences, or None where it is not an enabled add-on."""
    context = context or bpy.context
    addon = context.preferences.addons.get(ADDON_PACKAGE)
    return addon.preferences if addon is not None else None


@dataclass
class DeviceChoice:
    """The backend one bake's transport runs on, and what the report says about the device."""

    name: str  # 'gpu' or 'cpu'
    report: dict
    backend: TransportBackend = field(default=CPU_BACKEND)


def choose(context, requested: str) -> DeviceChoice:
    """The device for ``requested`` ('auto', 'gpu' or 'cpu', as operators.adapter.settings.resolve gives it)."""
    prefs = preferences(context)
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
    budget_mib = prefs.gpu_memory_mib if prefs is not None else PREFERENCE_SETTINGS["gpu_memory_mib"].default
    report["gpu_memory_budget_mib"] = budget_mib
    budget = int(budget_mib) << 20
    return DeviceChoice("gpu", report, GPUBackend(budget))
