"""Accumulation of the lighting passes on the GPU: twin of :func:`core.transport.passes.accumulate_passes`."""
from __future__ import annotations

import numpy as np

from . import runtime
from .gather import GROUP_SIZE

PASS_ORDER = ("lighting", "direct", "indirect", "irradiance")


def _build(info) -> None:
    info.image(0, "RGBA32F", "FLOAT_2D_ARRAY", "passes_out", qualifiers={"WRITE"})
    info.sampler(0, "FLOAT_2D_ARRAY", "irradiance_in")
    info.sampler(1, "FLOAT_2D", "albedo")
    for name in ("sample_width", "sample_count", "group_count", "per_group"):
        info.push_constant("INT", name)
    info.local_group_size(GROUP_SIZE, GROUP_SIZE)


def accumulate_passes(albedo: np.ndarray, wants, groups: dict, per_group: bool) -> dict:
    """Same contract as :func:`core.transport.passes.accumulate_passes`; values summed in float32."""
    if not groups:
        return {}
    from ..core.transport.passes import group_pass_name

    runtime.ensure_context()
    import gpu

    names = list(groups)
    count = len(albedo)
    width, height = runtime.sample_grid(count)
    layers = np.zeros((2 * len(names), height * width, 4), np.float32)
    for index, name in enumerate(names):
        layers[2 * index, :count, :3] = groups[name].direct
        layers[2 * index + 1, :count, :3] = groups[name].gathered
    with runtime.TextureSet() as resident:
        inputs = resident.upload(layers.reshape(-1, height, width, 4), layers=True)
        rho = resident.upload(runtime.to_grid(np.pad(np.asarray(albedo, np.float32), ((0, 0), (0, 1))),
                                              width, height))
        slots = 1 + (len(names) if per_group else 0)
        outputs = resident.empty(width, height, layers=4 * (1 + len(names)))
        program = runtime.shader("passes", _build)
        program.bind()
        program.image("passes_out", outputs)
        program.uniform_sampler("irradiance_in", inputs)
        program.uniform_sampler("albedo", rho)
        for key, value in (("sample_width", width), ("sample_count", count), ("group_count", len(names)),
                           ("per_group", int(per_group))):
            program.uniform_int(key, value)
        groups_xy = (-(-width // GROUP_SIZE), -(-height // GROUP_SIZE), 1)
        gpu.compute.dispatch(program, *groups_xy)

        per_pass = {}
        for slot in range(slots):
            for number, pass_name in enumerate(PASS_ORDER):
                if pass_name not in wants:
                    continue
                values = runtime.read_layer(resident, outputs, 4 * slot + number, width, height)
                values = values.reshape(-1, 4)[:count, :3].astype(np.float64)
                per_pass[pass_name if slot == 0 else group_pass_name(pass_name, names[slot - 1])] = values
        return per_pass
