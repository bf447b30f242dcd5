"""Direct light from lamps on the GPU: the twin of :func:`core.transport.direct.lamp_irradiance`.

The GPU evaluates every lamp (every virtual point of an area lamp) per sample and
applies the shadowing; the CPU keeps what needs the table or the ray tracer, exactly
as numpy does it: shadow fractions of local lamps (``core.visibility.shadows.shadow_fractions``,
counts per sample and region) and, with exact shadows, the shadow rays themselves
(uploaded as one bit per sample and virtual point).

Lamps integrated with the direct-light sampler (area lamps, suns with an angle, points
and spots with a radius: :func:`core.lights.lamps.lamp_points` above one) draw their
points per sample; those go through numpy's pass, and the GPU evaluates the hard lamps
(one point each) at texel centres. With exact shadows over texel footprints
(:attr:`core.transport.contract.SampleSet.footprint`, the default) every lamp is several
points a texel, and all of them go through numpy's pass. Light linking is applied to the
GPU's result per lamp, with the same receiver mask numpy uses, and shadow rays go to each lamp's blocker scene.

One dispatch per lamp; its virtual points are summed in float32 on the GPU and the
lamps in float64 on the CPU, like numpy. Samples are split into chunks when one
lamp's textures would not fit the GPU memory budget; every texture is freed when the
call returns, also on an error.
"""
from __future__ import annotations

import numpy as np

from ..core.lights.lamps import lamp_points, light_contributions
from ..core.transport import direct as cpu_direct
from . import runtime

GROUP_SIZE = 16  # local work group: 16 x 16 samples
# GPU memory one call may use (see gather.DEFAULT_BUDGET_BYTES).
DEFAULT_BUDGET_BYTES = 1 << 30
KINDS = {"SUN": 0, "POINT": 1, "SPOT": 2, "AREA": 3}
SHADOW_FRACTIONS, SHADOW_EXACT = 1, 2
TEXEL_BYTES = 16  # RGBA32F
POINTS_PER_LAYER = 64  # 4 channels x 16 bits of an exact integer in float32
# Per sample, always resident: positions, normals, geometric normals, the accumulator.
GEOMETRY_TEXELS = 4


def _build(info) -> None:
    info.image(0, "RGBA32F", "FLOAT_2D", "accumulated", qualifiers={"WRITE"})
    info.sampler(0, "FLOAT_2D", "positions")
    info.sampler(1, "FLOAT_2D", "normals")
    info.sampler(2, "FLOAT_2D", "geometric")
    info.sampler(3, "FLOAT_2D", "lamps")
    info.sampler(4, "FLOAT_2D_ARRAY", "shadow_data")
    info.sampler(5, "FLOAT_2D", "regions")
    for name in ("sample_width", "sample_count", "point_count", "shadow_mode", "region_count", "region_layers"):
        info.push_constant("INT", name)
    info.push_constant("FLOAT", "exponent")
    info.local_group_size(GROUP_SIZE, GROUP_SIZE)


def lamp_rows(light, origin: np.ndarray, area_light_samples: int) -> np.ndarray:
    """The lamp texture of one lamp: (P, 4, 4) float64, one row of 4 texels per virtual point.

    Holds only what does not depend on the sample, with the constants of
    :func:`core.lights.lamps.light_contributions` folded into an rgb scale. ``origin`` (3,)
    is subtracted from positions, as from the samples'.
    """
    color = np.asarray(light.color, np.float64)[:3]
    strength = max(float(light.strength), 0.0)
    if not np.isfinite(strength):
        raise ValueError(f"light {light.name!r} has a non-finite strength")
    if light.kind not in KINDS:
        raise ValueError(f"light {light.name!r}: unsupported kind {light.kind!r}")
    if light.kind == "AREA" or lamp_points(light, area_light_samples) > 1:
        raise ValueError(f"light {light.name!r}: its points are drawn per sample; numpy's pass evaluates it")
    direction = np.asarray(light.direction, np.float64)
    if light.kind == "SUN":
        places, scale = -direction[None], strength * color
    else:
        places, scale = np.asarray(light.position, np.float64)[None] - origin, strength / (4.0 * np.pi) * color
    rows = np.zeros((len(places), 4, 4))
    rows[:, 0, :3] = places
    rows[:, 0, 3] = KINDS[light.kind]
    rows[:, 1, :3] = scale
    rows[:, 2, :3] = direction
    if light.kind == "SPOT":
        half = light.spot_size / 2.0
        # cos(angle) - cos(half) = c0 - |from_light - axis|^2 / 2 for a unit from_light;
        # 1 - cos(half) as 2 sin^2(half / 2) keeps its digits for narrow cones.
        rows[:, 2, 3] = 2.0 * np.sin(half / 2.0) ** 2 + (direction @ direction - 1.0) / 2.0
        rows[:, 3, 0] = (1.0 - np.cos(half)) * light.spot_blend  # the band, as spot_mask computes it
    return rows


def _blocked_bits(sample_set, shadowing, light) -> tuple[np.ndarray, int]:
    """Which shadow rays of ``light`` are blocked, traced as numpy traces them.

    Returns (K, layers, 4) float32 exact integer bit masks (bit i of a channel: virtual
    point 16 * channel + 64 * layer + i) and the number of rays traced.
    """
    count = lamp_points(light, shadowing.area_light_samples)
    layers = -(-count // POINTS_PER_LAYER)
    bits = np.zeros((len(sample_set.position), 4 * layers), np.uint32)
    rays_traced = 0
    blockers = shadowing.blocker_scene(light)
    receives = shadowing.receivers(light, sample_set)
    # The samples' indices in the whole bake seed their scramble, as in numpy's pass.
    parts = light_contributions(light, sample_set.position, sample_set.normal, shadowing.area_light_samples,
                                sample_set.sample_ids(), shadowing.seed)
    for index, part in enumerate(parts):
        above = np.einsum("kd,kd->k", part.to_light, sample_set.geometric) > 0.0
        lit = above & np.any(part.irradiance > 0, axis=1)
        if receives is not None:
            lit &= receives
        rays = np.nonzero(lit)[0]
        if not len(rays) or blockers is None:
            continue
        blocked = cpu_direct.trace_shadow_rays(blockers, sample_set, part, rays)
        bits[rays[blocked], index // 16] |= np.uint32(1 << (index % 16))
        rays_traced += len(rays)
    return bits.astype(np.float32).reshape(len(sample_set.position), layers, 4), rays_traced


def _fraction_layers(fractions) -> np.ndarray:
    """(K, 2 * ceil(M / 4), 4) float32: lit then traced counts, 4 regions per texel."""
    samples, count = fractions.lit.shape
    layers = -(-count // 4)
    packed = np.zeros((samples, 2, 4 * layers), np.float32)
    packed[:, 0, :count] = fractions.lit
    packed[:, 1, :count] = fractions.traced
    return packed.reshape(samples, 2 * layers, 4)


def chunk_samples(samples: int, per_sample_bytes: int, fixed_bytes: int, budget_bytes: int) -> int:
    """Samples per chunk so one chunk's textures and the fixed ones fit ``budget_bytes``."""
    available = budget_bytes - fixed_bytes
    if available < per_sample_bytes:
        raise MemoryError(f"the GPU budget of {budget_bytes / 2**20:.0f} MiB cannot hold the lamp textures "
                          f"({fixed_bytes / 2**20:.2f} MiB) and one sample ({per_sample_bytes} bytes)")
    width = 2048  # runtime.sample_grid's: whole rows, so the padded grid stays within the budget
    chunk = min(samples, available // per_sample_bytes, width * runtime.MAX_TEXTURE_SIZE)
    if chunk > width:
        chunk -= chunk % width
    return max(1, int(chunk))


def lamp_irradiance(sample_set, shadowing, lights, report=None,
                    budget_bytes: int = DEFAULT_BUDGET_BYTES, spread: list | None = None) -> tuple[np.ndarray, int]:
    """(K, 3) float64 irradiance of ``lights`` and the shadow rays traced (int).

    Same contract as :func:`core.transport.direct.lamp_irradiance`: ``sample_set`` a
    SampleSet, shadows as ``shadowing`` (a Shadowing) says, ``report(fraction)`` after each lamp,
    the standard error appended to ``spread``. The lamps lit here, one point a sample, have none:
    only the lamps the numpy pass integrates over points do.
    """
    samples = len(sample_set.position)
    # Over texel footprints (exact shadows) every lamp is several points a texel: numpy's.
    # So do smooth faces (lit by the shading normal's horizon, their shadow rays lifted).
    over_footprints = ((shadowing.mode == "exact" and sample_set.footprint is not None)
                       or sample_set.terminator is not None)
    sampled = [light for light in lights if over_footprints or light.kind == "AREA"
               or lamp_points(light, shadowing.area_light_samples) > 1]
    if sampled:
        hard = [light for light in lights if not any(light is other for other in sampled)]
        # Progress shared by expected shadow rays, as the numpy pass weighs its lamps.
        sampled_cost = sum(cpu_direct.shadow_rays_per_sample(light, shadowing) for light in sampled)
        share = sampled_cost / (sampled_cost + len(hard))  # a hard lamp traces one ray a sample
        irradiance, rays = cpu_direct.lamp_irradiance(sample_set, shadowing, sampled,
                                                      None if report is None else lambda f: report(share * f), spread)
        if hard:
            more, more_rays = lamp_irradiance(sample_set, shadowing, hard, None if report is None else
                                              lambda f: report(share + (1.0 - share) * f), budget_bytes)
            irradiance, rays = irradiance + more, rays + more_rays
        return irradiance, rays
    irradiance = np.zeros((samples, 3))
    if spread is not None:
        spread.append(np.zeros((samples, 3)))
    if not lights:
        return irradiance, 0
    # Positions relative to the samples' centre: float32 then keeps its digits for the
    # offsets to lamps in scenes far from the world origin.
    origin = sample_set.position.mean(axis=0) if samples else np.zeros(3)
    rows = [lamp_rows(light, origin, shadowing.area_light_samples) for light in lights]  # raises as numpy would
    if samples == 0:
        for index in range(len(lights)):
            if report is not None:
                report((index + 1) / len(lights))
        return irradiance, 0
    runtime.ensure_context()
    import gpu

    mode = SHADOW_FRACTIONS if shadowing.mode == "fractions" else SHADOW_EXACT
    regions = shadowing.regions() if mode == SHADOW_FRACTIONS else None
    region_count = regions.count if regions is not None else 0
    region_layers = -(-region_count // 4)
    max_points = max(len(r) for r in rows)
    if mode == SHADOW_FRACTIONS:
        kinds = {light.kind == "SUN" for light in lights}
        # The suns' fractions stay resident next to a local lamp's when both kinds occur.
        shadow_layers = 2 * region_layers * len(kinds)
    else:
        shadow_layers = -(-max_points // POINTS_PER_LAYER)
    per_sample = TEXEL_BYTES * (GEOMETRY_TEXELS + shadow_layers)
    fixed = TEXEL_BYTES * (4 * max_points + max(region_count, 1))
    chunk = chunk_samples(samples, per_sample, fixed, budget_bytes)
    chunks = [(start, min(samples, start + chunk)) for start in range(0, samples, chunk)]
    # With one chunk, what does not change between lamps is uploaded once.
    resident = len(chunks) == 1

    # Textures kept for the whole call, with the arrays they were made from:
    # key -> (texture, array).
    lasting = {}
    sun_layers = None
    shadow_rays = 0

    def upload(array, as_layers=False, key=None):
        """A texture of ``array``; kept under ``key`` for later lamps when all samples are one chunk."""
        if key is not None and key in lasting:
            return lasting[key]
        made = runtime.float_texture(array() if callable(array) else array, as_layers)
        if key is not None and resident:
            lasting[key] = made
        return made

    def grid_layers(values, start, stop, width, height):
        """(K, L, 4) per-sample texels of one chunk as (L, height, width, 4)."""
        grid = np.zeros((height * width, values.shape[1], 4), np.float32)
        grid[:stop - start] = values[start:stop]
        return grid.reshape(height, width, values.shape[1], 4).transpose(2, 0, 1, 3)

    def geometry_grid(values, start, stop, width, height):
        return lambda: runtime.to_grid(np.pad(np.asarray(values[start:stop], np.float32), ((0, 0), (0, 1))),
                                       width, height)

    try:
        program = runtime.shader("direct", _build)
        centres = np.zeros((1, max(region_count, 1), 4), np.float32)
        if regions is not None:
            centres[0, :, :3] = regions.centres
        regions_texture = upload(centres, key="regions")
        relative = sample_set.position - origin
        for light_index, (light, lamp) in enumerate(zip(lights, rows)):
            shadow_key = None
            lamp_mode = mode if light.casts_shadows else 0  # 0: no shadow at all, as numpy
            receives = shadowing.receivers(light, sample_set)
            if lamp_mode == 0:
                shadow_values = np.zeros((samples, 1, 4), np.float32)
            elif mode == SHADOW_FRACTIONS:
                if light.kind == "SUN":
                    if sun_layers is None:
                        sun_layers = _fraction_layers(shadowing.distant_fractions())
                    shadow_values, shadow_key = sun_layers, "sun"
                else:
                    offsets = sample_set.position - np.asarray(light.position, np.float64)
                    light_distance = np.linalg.norm(offsets, axis=1)
                    shadow_values = _fraction_layers(shadowing.local_fractions(light_distance))
            else:
                shadow_values, rays = _blocked_bits(sample_set, shadowing, light)
                shadow_rays += rays
            lamp_texture = upload(lamp.astype(np.float32))
            for start, stop in chunks:
                width, height = runtime.sample_grid(stop - start)
                positions = upload(geometry_grid(relative, start, stop, width, height), key="positions")
                normals = upload(geometry_grid(sample_set.normal, start, stop, width, height), key="normals")
                geometric = upload(geometry_grid(sample_set.geometric, start, stop, width, height), key="geometric")
                accumulated = lasting.get("accumulated") or (runtime.empty_texture(width, height), None)
                if resident:
                    lasting["accumulated"] = accumulated
                shadow = upload(lambda values=shadow_values, start=start, stop=stop, width=width, height=height:
                                grid_layers(values, start, stop, width, height), True, key=shadow_key)
                program.bind()
                program.image("accumulated", accumulated[0])
                program.uniform_sampler("positions", positions[0])
                program.uniform_sampler("normals", normals[0])
                program.uniform_sampler("geometric", geometric[0])
                program.uniform_sampler("lamps", lamp_texture[0])
                program.uniform_sampler("shadow_data", shadow[0])
                program.uniform_sampler("regions", regions_texture[0])
                for name, value in (("sample_width", width), ("sample_count", stop - start),
                                    ("point_count", len(lamp)), ("shadow_mode", lamp_mode),
                                    ("region_count", region_count), ("region_layers", region_layers)):
                    program.uniform_int(name, value)
                program.uniform_float("exponent", regions.exponent if regions is not None else 1.0)
                gpu.compute.dispatch(program, -(-width // GROUP_SIZE), -(-height // GROUP_SIZE), 1)
                read = runtime.read_texture(accumulated[0]).reshape(-1, 4)[:stop - start, :3]
                irradiance[start:stop] += read if receives is None else read * receives[start:stop, None]
                # Outside one resident chunk these are the last references: the GPU memory
                # goes before the next chunk's uploads.
                del positions, normals, geometric, accumulated, shadow
            del lamp_texture, shadow_values
            if report is not None:
                report((light_index + 1) / len(lights))
        return irradiance, shadow_rays
    finally:
        lasting.clear()
