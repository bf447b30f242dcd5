"""Check the numpy Principled BSDF model (core/appearance/fit.py) against Cycles itself.

Renders a flat tile with a Principled BSDF of several parameter sets under a sun (strength 1,
angle 0) and an orthographic camera along -v, with ``benchmarks.brdf_reference.cycles_brdf``
(direct light only, box filter, no denoising, no adaptive sampling, EXR read back linear), and
compares f = L / cos theta_l with :func:`core.appearance.fit.principled_brdf` at the same pairs.
The material is this module's own (the reference harness's only knows base colour and
roughness): all inputs the model knows, and a constant Tangent (+x), which the model assumes.

    .venv/bin/python benchmarks/principled_check.py [--samples 4] [--json out.json] [--sets NAME ...]
    NUMBA_CACHE_DIR=/tmp/numba-fit .venv/bin/python benchmarks/principled_check.py --tiles [--no-cycles]

Prints, per parameter set, the relative RMSE (weighted by cos theta_l cos theta_v) and the worst
relative error of one pair/channel, model against Cycles. A sun of angle 0 is a delta light, so
with bounces 0 every camera sample is an exact BSDF evaluation: the renders are noise-free up to
pixel coverage, and a few samples suffice. The "diffuse rough" sets check the Oren-Nayar model of
Diffuse Roughness (coloured, so that the tint of its multiple-scattering term is checked too).

``--tiles`` adds what Diffuse Roughness does for the fit (core.appearance.fit.fit_principled) on
two simulated tiles (core.appearance.gonio.simulate_brdf: 64 light x 64 view hemisphere
directions, 128 global directions, 2 bounces, resolution 48): a Lambert V-groove with 45-degree
walls (brdf_tiles.v_groove_tile(0.5), albedo (0.30, 0.40, 0.55)), the same V-groove averaged over
12 azimuths of the tile (an isotropic V-groove surface, Oren-Nayar's own assumption) and the woven
tile (brdf_tiles.woven_tile(), fibres (0.55, 0.12, 0.08), specular 0.1, GGX roughness 0.4, smooth).
Each is fitted as operators/adapter/tile_io.py does (at most 2500 pairs, the BRDF divided by the
share of light that does not pass through the gaps) without and with Diffuse Roughness, and the
relative RMSE of both is printed. About 3 minutes on 2 cores (the woven tile's simulation).
"""
from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)

import bpy  # noqa: E402

from benchmarks import brdf_reference  # noqa: E402
from benchmarks.brdf_reference import direction  # noqa: E402
from benchmarks.brdf_tiles import flat_tile  # noqa: E402
from core.appearance.fit import PrincipledParams, principled_brdf, weighted_rmse  # noqa: E402

PAIRS = [(direction(tl, pl), direction(tv, pv)) for tl, pl, tv, pv in [
    (0, 0, 0, 0), (30, 0, 30, 180), (45, 0, 20, 90), (60, 0, 60, 180),
    (20, 45, 50, 200), (70, 10, 40, 300), (40, 120, 40, 120), (55, 200, 65, 60)]]

SETS = {
    "grey rough 0.5": PrincipledParams(base_color=np.full(3, 0.8), roughness=0.5),
    "colour rough 0.2, spec 0.8": PrincipledParams(base_color=np.array([0.8, 0.5, 0.2]), roughness=0.2,
                                                   specular_ior_level=0.8),
    "sheen 1 (tint 1 .6 .3, rough .4)": PrincipledParams(base_color=np.full(3, 0.3), roughness=0.5,
                                                         sheen_weight=1.0, sheen_roughness=0.4,
                                                         sheen_tint=np.array([1.0, 0.6, 0.3])),
    "aniso 0.8 rot 0": PrincipledParams(base_color=np.full(3, 0.5), roughness=0.3, anisotropic=0.8),
    "aniso 0.8 rot 0.125": PrincipledParams(base_color=np.full(3, 0.5), roughness=0.3, anisotropic=0.8,
                                            anisotropic_rotation=0.125),
    "metallic 1 rough 0.4": PrincipledParams(base_color=np.array([0.9, 0.6, 0.3]), roughness=0.4, metallic=1.0),
    # Specular IOR Level 0: no specular layer (F0 = 0), the diffuse closure alone
    "diffuse rough 0.5 (no specular)": PrincipledParams(base_color=np.array([0.8, 0.5, 0.2]), roughness=0.5,
                                                        specular_ior_level=0.0, diffuse_roughness=0.5),
    "diffuse rough 1 (no specular)": PrincipledParams(base_color=np.array([0.9, 0.6, 0.25]), roughness=0.5,
                                                      specular_ior_level=0.0, diffuse_roughness=1.0),
    "diffuse rough 1, spec rough 0.3": PrincipledParams(base_color=np.array([0.3, 0.5, 0.8]), roughness=0.3,
                                                        diffuse_roughness=1.0),
}


def _material_factory(p: PrincipledParams):
    def make(albedo, roughness, transmission=0.0):  # the harness's signature; only p counts
        from tools.blender_compat import compat

        material = bpy.data.materials.new("Principled check")
        tree = compat.ensure_node_tree(material)
        tree.nodes.clear()
        out = tree.nodes.new("ShaderNodeOutputMaterial")
        bsdf = tree.nodes.new("ShaderNodeBsdfPrincipled")
        inputs = bsdf.inputs
        inputs["Base Color"].default_value = (*[float(c) for c in p.base_color], 1.0)
        inputs["Roughness"].default_value = float(p.roughness)
        inputs["Metallic"].default_value = float(p.metallic)
        inputs["IOR"].default_value = float(p.ior)
        inputs["Specular IOR Level"].default_value = float(p.specular_ior_level)
        inputs["Anisotropic"].default_value = float(p.anisotropic)
        inputs["Anisotropic Rotation"].default_value = float(p.anisotropic_rotation)
        inputs["Sheen Weight"].default_value = float(p.sheen_weight)
        inputs["Sheen Roughness"].default_value = float(p.sheen_roughness)
        inputs["Sheen Tint"].default_value = (*[float(c) for c in p.sheen_tint], 1.0)
        inputs["Transmission Weight"].default_value = float(p.transmission_weight)
        inputs["Diffuse Roughness"].default_value = float(p.diffuse_roughness)
        tangent = tree.nodes.new("ShaderNodeCombineXYZ")
        tangent.inputs["X"].default_value = 1.0
        tree.links.new(tangent.outputs["Vector"], inputs["Tangent"])
        tree.links.new(bsdf.outputs["BSDF"], out.inputs["Surface"])
        return material
    return make


def check(samples: int = 4, resolution: int = 32, sets=None) -> dict:
    light = np.array([p[0] for p in PAIRS])
    view = np.array([p[1] for p in PAIRS])
    original = brdf_reference._material
    results = {}
    try:
        for name, params in SETS.items():
            if sets and name not in sets:
                continue
            brdf_reference._material = _material_factory(params)
            tile = flat_tile()
            ref = brdf_reference.cycles_brdf(*tile, albedo=0.8, pairs=PAIRS, samples=samples,
                                             resolution=resolution, roughness=0.5, bounces=0, repeats=1)
            model = principled_brdf(light, view, params)
            rmse, _ = weighted_rmse(model, ref.values, light, view)
            rel = np.abs(model - ref.values) / np.maximum(np.abs(ref.values), 1e-9)
            results[name] = {"rmse": float(rmse), "max_rel": float(rel.max()),
                             "cycles": ref.values.tolist(), "model": model.tolist(),
                             "noise": ref.noise.tolist()}
            print(f"{name:36s} rel. RMSE {100 * rmse:6.2f}%  worst pair/channel {100 * rel.max():6.2f}%"
                  f"  (Cycles noise {100 * float((ref.noise / np.maximum(ref.values, 1e-9)).max()):.2f}%)",
                  flush=True)
    finally:
        brdf_reference._material = original
    return results


def _tile_brdfs():
    """(name, light, view, values (L, V, 3), gaps) of the simulated tiles (see the module doc)."""
    import math

    from benchmarks.brdf_tiles import v_groove_tile, woven_tile
    from core.appearance import gonio
    from core.appearance.tile import Tile

    directions = gonio.hemisphere_directions(64)
    settings = gonio.GonioSettings(directions=128, bounces=2, resolution=48)

    def gaps_of(result):
        return float(result.transparency[result.light[:, 2] > 0].mean())

    groove = Tile.of(*v_groove_tile(0.5), albedo=(0.30, 0.40, 0.55))
    result = gonio.simulate_brdf(groove, directions, directions, settings)
    yield "V-groove 45 deg, Lambert", result.light, result.view, result.values, gaps_of(result)
    turns, values = 12, 0.0
    for k in range(turns):
        a = math.pi * k / turns
        rotation = np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])
        turned = directions @ rotation.T
        values = values + gonio.simulate_brdf(groove, turned, turned, settings).values
    yield "V-groove, 12 azimuths averaged", directions, directions, values / turns, 0.0
    weave = Tile.of(*woven_tile(), albedo=(0.55, 0.12, 0.08), specular=0.1, roughness=0.4, smooth=True)
    result = gonio.simulate_brdf(weave, directions, directions, settings)
    yield "woven", result.light, result.view, result.values, gaps_of(result)


def tile_fits() -> dict:
    """The fits of the simulated tiles without and with Diffuse Roughness (see the module doc)."""
    import time

    from core.appearance.fit import fit_principled

    results = {}
    for name, light, view, values, gaps in _tile_brdfs():
        pairs_light = np.repeat(light, len(view), axis=0)
        pairs_view = np.tile(view, (len(light), 1))
        rows = np.nonzero((pairs_light[:, 2] > 0) & (pairs_view[:, 2] > 0))[0]
        rows = rows[::max(1, len(rows) // 2500)]
        f = values.reshape(-1, 3)[rows] / max(1.0 - gaps, 1e-3)
        entry = {}
        for label, on in (("before", False), ("after", True)):
            started = time.perf_counter()
            fit = fit_principled(pairs_light[rows], pairs_view[rows], f, try_diffuse_roughness=on)
            entry[label] = {"rmse": float(fit.rmse), "model": fit.model,
                            "diffuse_roughness": float(fit.diffuse_roughness),
                            "base_color": [float(c) for c in fit.base_color], "roughness": float(fit.roughness),
                            "specular_ior_level": float(fit.specular_ior_level),
                            "candidates": {k: float(v) for k, v in fit.candidates.items()},
                            "seconds": round(time.perf_counter() - started, 1)}
        b, a = entry["before"], entry["after"]
        print(f"{name:32s} fit rel. RMSE {100 * b['rmse']:6.2f}% without Diffuse Roughness ({b['model']}), "
              f"{100 * a['rmse']:6.2f}% with ({a['model']}, Diffuse Roughness {a['diffuse_roughness']:.3f})",
              flush=True)
        results[name] = entry
    return results


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--samples", type=int, default=4)
    parser.add_argument("--resolution", type=int, default=32)
    parser.add_argument("--json", default=None)
    parser.add_argument("--sets", nargs="*", default=None, help="only these parameter sets (names as printed)")
    parser.add_argument("--tiles", action="store_true", help="also the tile fits without and with Diffuse Roughness")
    parser.add_argument("--no-cycles", action="store_true", help="skip the Cycles renders (with --tiles)")
    args = parser.parse_args(argv)
    results = {}
    if not args.no_cycles:
        results["cycles"] = check(args.samples, args.resolution, args.sets)
    if args.tiles:
        results["tiles"] = tile_fits()
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
