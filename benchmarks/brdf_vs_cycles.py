"""VisiBake's simulated tile BRDFs against Cycles, and how fast they come (the paper's section 7.1).

What is compared
----------------
The BRDF of a periodic micro-geometry tile, f(l, v) in 1/sr: the mean outgoing radiance of
one period seen along v, over the irradiance E cos(theta_l) that a sun of unit irradiance
along l gives the macro plane. VisiBake computes it with ``core.appearance.gonio.simulate_brdf``
(precomputed visibility tables, K inter-reflections after the direct light); the reference
is Cycles rendering the repeated tile (``benchmarks/brdf_reference.py``: orthographic
camera along v, sun along l, the central period averaged exactly, K diffuse bounces after
the direct light, the same meaning of K). Both see the same triangles with the same
Lambert material (albedo 0.8).

1. Accuracy, per tile, over the (l, v) pairs of ``default_pairs(20)`` (four fixed ones,
   then pseudo-random ones up to 75 degrees), 4 bounces:
   (a) the V-groove (depth 0.5 x period, flat shading), (b) the woven tile (plain weave,
   smooth shading in both renderers). Cycles at ``--samples`` per pixel (16) x 2 seeds,
   64 px, and again at ``--ref-samples`` (64) as a less noisy cross-check; VisiBake at its
   defaults (128 directions, resolution 64, 128 view rays) and finer (256 directions).
   Error: relative RMSE = sqrt(mean_pairs((vb - cy)^2)) / mean_pairs(cy) on the first
   channel (all three are equal: grey albedo), beside Cycles' own relative noise
   sqrt(mean(noise^2)) / mean(cy) (noise = the standard error of the Cycles value), the
   per-pair relative errors vb / cy - 1 and the mean ratio mean(vb / cy). VisiBake is run
   once per setting for all lights x all views (a 20 x 20 grid, of which the 20 diagonal
   pairs are compared): its times are for the whole grid. Target: relative RMSE <= 3%.
   Checks: with 0 bounces, both against the closed-form direct BRDF of the V-groove
   (``brdf_tiles.v_groove_direct_brdf``): the bounce counting of the two agrees.
2. Slices (``--plot``): a light at theta_l = 45 deg, phi_l = 0, views in the plane of
   incidence, theta_v from -75 to 75 deg (negative: phi_v = 180, the forward side);
   VisiBake as a line (61 views), Cycles as points with +-2 standard errors (7 views).
3. Translucent (``translucent`` in the JSON; ``--only translucent`` runs it alone and
   updates that key of the existing JSON, leaving the rest as it was): the open V-groove
   sheet (``v_groove_tile(0.5)``, a single-layer height field) with albedo 0.8 and
   transmission 0.5 (a thin sheet: (1 - t) albedo / pi reflected, t albedo / pi to the
   other side; Cycles: Add Shader(Diffuse 0.4, Translucent 0.4)), 4 bounces, over 20 (l, v)
   pairs on the whole sphere (``sphere_pairs``): reflection from above, transmission with
   the light above and the view below, transmission with the light below and the view
   above, reflection from below, five of each (theta up to 75 deg from the normal on the
   direction's side). Reported as in 1., and per kind of pair (``by_kind``).
4. Speed: ``simulate_brdf`` for 100 light x 100 view directions (``hemisphere_directions(100)``
   both, 10,000 samples) on a 64 x 64 heightfield (0.05 sin(2 pi x) cos(4 pi y) + uniform
   noise of amplitude 0.004, smooth shading so that its samples at resolution 64 are its
   65 x 65 vertices), 128 directions, 2 bounces; Lambert (specular 0) and glossy (specular
   0.3, the paper's Phong lobe of exponent 8). Target: <= 60 s for the 10,000 samples.
   Per-stage seconds from ``BRDFSamples.stats``. For comparison, Cycles' seconds per (l, v) pair on the same
   tile (Lambert, 2 bounces, the accuracy runs' samples) and its noise there.

Times are wall seconds on this machine (``machine`` in the JSON), CPU only. The compiled
kernels are loaded (or compiled) by a tiny run before anything is timed
(``kernel_warmup_s``).

Reproduce
---------
    export NUMBA_CACHE_DIR=/tmp/numba-cache     # any writable folder
    .venv/bin/python benchmarks/brdf_vs_cycles.py \\
        [--out docs/appearance/brdf_vs_cycles.json] [--plot docs/appearance/brdf_slices.png]
    .venv/bin/python benchmarks/brdf_vs_cycles.py --quick     # 4 pairs, low samples: a smoke test
    .venv/bin/python benchmarks/brdf_vs_cycles.py --only translucent   # the translucent case alone
    make bench BENCH_PROFILE=appearance

``--quick`` writes to benchmarks/results/ unless --out / --plot are given.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import sys
import time
from datetime import datetime, timezone

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)

import bpy  # noqa: E402,F401  (the Cycles harness needs it loaded first)

from benchmarks import brdf_tiles  # noqa: E402
from benchmarks.brdf_reference import _machine, cycles_brdf, default_pairs, direction  # noqa: E402
from core.appearance.gonio import GonioSettings, hemisphere_directions, simulate_brdf  # noqa: E402
from core.appearance.tile import Tile  # noqa: E402

ALBEDO = 0.8
V_DEPTH = 0.5
TARGET_RMSE = 0.03
TARGET_SPEED_S = 60.0
SLICE_LIGHT = (45.0, 0.0)
TRANSMISSION = 0.5
# The kinds of (l, v) pair on the sphere: (light above, view above) and so on.
PAIR_KINDS = {"reflect_above": (1, 1), "transmit_down": (1, -1), "transmit_up": (-1, 1), "reflect_below": (-1, -1)}


@contextlib.contextmanager
def quiet():
    """Cycles prints a line per render on the C stdout: send fd 1 to /dev/null meanwhile."""
    sys.stdout.flush()
    saved = os.dup(1)
    null = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(null, 1)
        yield
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)
        os.close(null)


def tiles():
    """name -> (positions, triangles, period, smooth, description)."""
    vg = brdf_tiles.v_groove_tile(V_DEPTH)
    woven = brdf_tiles.woven_tile()
    return {"vgroove": (*vg, False, f"V-groove, depth {V_DEPTH} x period, flat shading"),
            "woven": (*woven, True, "plain weave (woven_tile defaults), smooth shading")}


def sphere_pairs(count: int, max_theta: float = 75.0, seed: int = 1):
    """``count`` (light, view) pairs over the whole sphere, (count, 2, 3), and their kinds
    (PAIR_KINDS, cycling in that order): the first of each kind fixed (45 / 30 deg on
    opposite azimuths; normal through normal; 45 below / 30 above on one azimuth; 60 / 45
    below at azimuths 90 deg apart), then pseudo-random ones (fixed seed), theta from the
    normal on the direction's own side uniform in [0, max_theta], azimuth uniform."""
    fixed = [((45, 0), (30, 180)), ((0, 0), (0, 0)), ((45, 0), (30, 0)), ((60, 30), (45, 120))]
    kinds = list(PAIR_KINDS)
    rng = np.random.default_rng(seed)
    pairs, labels = [], []
    for k in range(count):
        kind = kinds[k % len(kinds)]
        if k < len(fixed):
            (tl, pl), (tv, pv) = fixed[k]
        else:
            tl, tv = rng.uniform(0.0, max_theta, 2)
            pl, pv = rng.uniform(0.0, 360.0, 2)
        side_l, side_v = PAIR_KINDS[kind]
        pairs.append((direction(tl if side_l > 0 else 180.0 - tl, pl), direction(tv if side_v > 0 else 180.0 - tv, pv)))
        labels.append(kind)
    return np.array(pairs, np.float64).reshape(-1, 2, 3), labels


def heightfield(n: int = 64):
    x = np.arange(n) / n
    xx, yy = np.meshgrid(x, x)  # heights[j, i] at (x_i, y_j)
    noise = 0.004 * np.random.default_rng(0).uniform(-1.0, 1.0, (n, n))
    return brdf_tiles.heightfield_tile(0.05 * np.sin(2 * np.pi * xx) * np.cos(4 * np.pi * yy) + noise)


def run_cycles(tile, pairs, samples, bounces, smooth, transmission=0.0):
    positions, triangles, period = tile
    with quiet():
        ref = cycles_brdf(positions, triangles, period, ALBEDO, pairs, samples=samples, bounces=bounces,
                          smooth=smooth, transmission=transmission)
    return ref


def run_visibake(positions, triangles, period, smooth, lights, views, settings: GonioSettings, **material):
    tile = Tile.of(positions, triangles, period=period, albedo=ALBEDO, smooth=smooth, **material)
    start = time.perf_counter()
    result = simulate_brdf(tile, lights, views, settings)
    return result, time.perf_counter() - start


def compare(vb: np.ndarray, cy: np.ndarray, noise: np.ndarray) -> dict:
    """Errors of vb against cy (first channel), beside cy's own noise."""
    vb, cy, noise = vb[:, 0], cy[:, 0], noise[:, 0]
    mean = float(cy.mean())
    return {
        "rel_rmse": float(np.sqrt(np.mean((vb - cy) ** 2)) / mean),
        "cycles_rel_noise_rms": float(np.sqrt(np.mean(noise ** 2)) / mean),
        "mean_ratio": float(np.mean(vb / cy)),
        "max_abs_rel_error": float(np.max(np.abs(vb / cy - 1.0))),
        "rel_errors": (vb / cy - 1.0).tolist(),
    }


def stats_of(result, wall):
    return {"wall_s": round(wall, 3), **{k: v for k, v in result.stats.items()}}


def accuracy(name, spec, pairs, args, log, transmission=0.0):
    positions, triangles, period, smooth, description = spec
    out = {"tile": description, "smooth": smooth, "triangles": int(len(triangles)), "albedo": ALBEDO,
           "bounces": args.bounces}
    material = {}
    if transmission > 0.0:
        out["transmission"] = transmission
        material["transmission"] = transmission
    cy = run_cycles((positions, triangles, period), pairs, args.samples, args.bounces, smooth, transmission)
    rel_noise = cy.noise[:, 0] / cy.values[:, 0]
    out["cycles"] = {"samples": args.samples, "seeds": 2, "resolution": 64, "values": cy.values[:, 0].tolist(),
                     "noise": cy.noise[:, 0].tolist(), "rel_noise": rel_noise.tolist(),
                     "max_rel_noise": float(rel_noise.max()), "coverage": cy.coverage.tolist(),
                     "seconds": cy.seconds.tolist(), "total_s": float(cy.seconds.sum()),
                     "s_per_pair": float(cy.seconds.mean()), "settings": cy.settings}
    log(f"[{name}] Cycles {args.samples} spp: {cy.seconds.sum():.1f} s, relative noise max "
        f"{100 * rel_noise.max():.2f}%")
    references = {"cycles": cy}
    if args.ref_samples:
        hi = run_cycles((positions, triangles, period), pairs, args.ref_samples, args.bounces, smooth, transmission)
        out["cycles_ref"] = {"samples": args.ref_samples, "values": hi.values[:, 0].tolist(),
                             "noise": hi.noise[:, 0].tolist(), "total_s": float(hi.seconds.sum()),
                             "max_rel_noise": float((hi.noise[:, 0] / hi.values[:, 0]).max()),
                             "vs_cycles": compare(cy.values, hi.values, hi.noise)}
        references["cycles_ref"] = hi
        log(f"[{name}] Cycles {args.ref_samples} spp: {hi.seconds.sum():.1f} s")
    out["visibake"] = {}
    for label, settings in args.vb_settings:
        result, wall = run_visibake(positions, triangles, period, smooth, pairs[:, 0], pairs[:, 1], settings,
                                    **material)
        values = np.stack([result.values[i, i] for i in range(len(pairs))])
        entry = {"settings": vars(settings).copy(), "values": values[:, 0].tolist(),
                 "grid": f"{len(pairs)} lights x {len(pairs)} views", "stats": stats_of(result, wall),
                 "warnings": result.warnings}
        for ref_name, ref in references.items():
            entry[f"vs_{ref_name}"] = compare(values, ref.values, ref.noise)
        out["visibake"][label] = entry
        c = entry["vs_cycles"]
        log(f"[{name}] VisiBake {label}: {wall:.1f} s, rel RMSE {100 * c['rel_rmse']:.2f}% (Cycles noise "
            f"{100 * c['cycles_rel_noise_rms']:.2f}%), mean ratio {c['mean_ratio']:.4f}")
    return out


def translucent(args, log):
    """The open V-groove sheet, translucent, over the whole sphere (item 3 of the module doc)."""
    pairs, kinds = sphere_pairs(args.translucent_pairs)
    positions, triangles, period = brdf_tiles.v_groove_tile(V_DEPTH)
    spec = (positions, triangles, period, False,
            f"open V-groove sheet (v_groove_tile({V_DEPTH}), one layer), flat shading, transmission {TRANSMISSION}")
    started = time.perf_counter()
    out = accuracy("translucent", spec, pairs, args, log, transmission=TRANSMISSION)
    out["pairs"] = pairs.tolist()
    out["pairs_theta_phi_deg"] = [[[math.degrees(math.acos(d[2])), math.degrees(math.atan2(d[1], d[0])) % 360]
                                   for d in pair] for pair in pairs]
    out["kinds"] = kinds
    out["kind_meaning"] = {kind: f"light {'above' if sl > 0 else 'below'}, view {'above' if sv > 0 else 'below'}"
                           for kind, (sl, sv) in PAIR_KINDS.items()}
    cy = np.asarray(out["cycles"]["values"])
    noise = np.asarray(out["cycles"]["noise"])
    for label, entry in out["visibake"].items():
        vb = np.asarray(entry["values"])
        entry["by_kind"] = {}
        for kind in PAIR_KINDS:
            rows = np.array([k == kind for k in kinds])
            if not rows.any():
                continue
            c = compare(vb[rows, None], cy[rows, None], noise[rows, None])
            entry["by_kind"][kind] = {key: c[key] for key in ("rel_rmse", "cycles_rel_noise_rms", "mean_ratio",
                                                              "max_abs_rel_error")}
            log(f"[translucent] VisiBake {label} {kind}: rel RMSE {100 * c['rel_rmse']:.2f}% (Cycles noise "
                f"{100 * c['cycles_rel_noise_rms']:.2f}%), mean ratio {c['mean_ratio']:.4f}")
    out["total_s"] = round(time.perf_counter() - started, 1)
    return out


def direct_check(pairs, args, log):
    """0 bounces on the V-groove: Cycles and VisiBake against the closed form."""
    positions, triangles, period = brdf_tiles.v_groove_tile(V_DEPTH)
    exact = np.array([float(np.ravel(brdf_tiles.v_groove_direct_brdf(V_DEPTH, ALBEDO, l, v))[0]) for l, v in pairs])
    cy = run_cycles((positions, triangles, period), pairs, args.samples, 0, False)
    settings = GonioSettings(directions=128, bounces=0, resolution=64, view_rays=128)
    result, wall = run_visibake(positions, triangles, period, False, pairs[:, 0], pairs[:, 1], settings)
    vb = np.array([result.values[i, i, 0] for i in range(len(pairs))])
    mean = exact.mean()
    out = {"closed_form": exact.tolist(), "cycles": cy.values[:, 0].tolist(), "cycles_noise": cy.noise[:, 0].tolist(),
           "visibake": vb.tolist(),
           "cycles_rel_rmse": float(np.sqrt(np.mean((cy.values[:, 0] - exact) ** 2)) / mean),
           "visibake_rel_rmse": float(np.sqrt(np.mean((vb - exact) ** 2)) / mean),
           "cycles_max_abs_rel_error": float(np.max(np.abs(cy.values[:, 0] / exact - 1.0)[exact > 1e-3])),
           "visibake_max_abs_rel_error": float(np.max(np.abs(vb / exact - 1.0)[exact > 1e-3])),
           "note": "max_abs_rel_error over the pairs whose closed form is > 1e-3 / sr"}
    log(f"[direct] 0 bounces vs closed form: Cycles rel RMSE {100 * out['cycles_rel_rmse']:.3f}%, VisiBake "
        f"{100 * out['visibake_rel_rmse']:.3f}%")
    return out


def slices(spec, args):
    positions, triangles, period, smooth, _ = spec
    light = direction(*SLICE_LIGHT)
    signed_line = np.linspace(-75.0, 75.0, args.slice_views)
    signed_points = np.linspace(-75.0, 75.0, args.slice_points)

    def view(t):
        return direction(abs(t), 0.0 if t >= 0 else 180.0)

    settings = GonioSettings(directions=128, bounces=args.bounces, resolution=64, view_rays=128)
    views = np.array([view(t) for t in signed_line])
    result, wall = run_visibake(positions, triangles, period, smooth, light[None], views, settings)
    pairs = np.array([(light, view(t)) for t in signed_points])
    cy = run_cycles((positions, triangles, period), pairs, args.samples, args.bounces, smooth)
    return {"light_theta_phi": list(SLICE_LIGHT), "theta_v_line": signed_line.tolist(),
            "visibake": result.values[0, :, 0].tolist(), "visibake_s": round(wall, 3),
            "theta_v_points": signed_points.tolist(), "cycles": cy.values[:, 0].tolist(),
            "cycles_noise": cy.noise[:, 0].tolist(), "cycles_s": float(cy.seconds.sum())}


def plot(data, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(data)
    fig, axes = plt.subplots(1, len(names), figsize=(5.2 * len(names), 3.8), dpi=100)
    for ax, name in zip(np.atleast_1d(axes), names):
        s = data[name]
        ax.plot(s["theta_v_line"], s["visibake"], "-", color="C0", label="VisiBake (128 dirs, res 64)")
        ax.errorbar(s["theta_v_points"], s["cycles"], yerr=2 * np.asarray(s["cycles_noise"]), fmt="o", color="C3",
                    ms=5, capsize=3, label="Cycles (+-2 s.e.)")
        ax.set_title(f"{s['title']}: $\\theta_l$ = {SLICE_LIGHT[0]:.0f}°, $\\phi_l$ = 0, albedo {ALBEDO}, 4 bounces")
        ax.set_xlabel(r"$\theta_v$ (°; < 0: $\phi_v$ = 180°, > 0: $\phi_v$ = 0)")
        ax.set_ylabel("BRDF (1/sr)")
        ax.set_ylim(bottom=0)
        ax.axvline(0, color="0.8", lw=0.8)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    fig.savefig(path)
    plt.close(fig)


def speed(args, log):
    positions, triangles, period = heightfield(64)
    dirs = hemisphere_directions(args.speed_directions)
    settings = GonioSettings(directions=128, bounces=2, resolution=64, view_rays=128)
    out = {"tile": "64 x 64 heightfield: 0.05 sin(2 pi x) cos(4 pi y) + 0.004 uniform noise, smooth shading",
           "lights": len(dirs), "views": len(dirs), "samples": len(dirs) ** 2, "settings": vars(settings).copy(),
           "target_s": TARGET_SPEED_S}
    for label, material in (("lambert", {"specular": 0.0}),
                            ("glossy", {"specular": 0.3, "roughness": -1.0, "phong_exponent": 8.0})):
        result, wall = run_visibake(positions, triangles, period, True, dirs, dirs, settings, **material)
        out[label] = {"material": material, "stats": stats_of(result, wall),
                      "s_per_sample": wall / len(dirs) ** 2, "meets_target": wall <= TARGET_SPEED_S}
        log(f"[speed] {label}: {wall:.1f} s for {len(dirs) ** 2} samples  {result.stats}")
    pairs = default_pairs(args.speed_cycles_pairs)
    cy = run_cycles((positions, triangles, period), pairs, args.samples, 2, True)
    rel = cy.noise[:, 0] / cy.values[:, 0]
    per_pair = float(cy.seconds.mean())
    out["cycles"] = {"pairs": len(pairs), "samples": args.samples, "seeds": 2, "bounces": 2, "material": "Lambert",
                     "s_per_pair": per_pair, "rel_noise": rel.tolist(), "max_rel_noise": float(rel.max()),
                     "values": cy.values[:, 0].tolist(),
                     "s_for_same_samples": per_pair * len(dirs) ** 2}
    for label in ("lambert", "glossy"):
        out[label]["cycles_over_visibake"] = per_pair / out[label]["s_per_sample"]
    log(f"[speed] Cycles: {per_pair:.3f} s per pair (max noise {100 * rel.max():.2f}%), "
        f"x{out['lambert']['cycles_over_visibake']:.0f} VisiBake Lambert, "
        f"x{out['glossy']['cycles_over_visibake']:.0f} glossy")
    return out


def warm_up() -> float:
    """Load (or compile) every kernel simulate_brdf uses, Lambert and glossy, outside the timings."""
    start = time.perf_counter()
    positions, triangles, period = brdf_tiles.v_groove_tile(V_DEPTH)
    tiny = GonioSettings(directions=16, bounces=2, resolution=4, view_rays=8)
    dirs = hemisphere_directions(2)
    for specular in (0.0, 0.3):
        run_visibake(positions, triangles, period, False, dirs, dirs, tiny, specular=specular)
    return round(time.perf_counter() - start, 3)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="4 pairs and low samples: a smoke test (< 1 min)")
    parser.add_argument("--out", default=None, help="JSON (default docs/appearance/brdf_vs_cycles.json)")
    parser.add_argument("--plot", default=None, help="PNG of the slices (default docs/appearance/brdf_slices.png)")
    parser.add_argument("--only", choices=("translucent",), default=None,
                        help="run this case alone and update its key in the existing JSON (--out)")
    args = parser.parse_args(argv)
    quick = args.quick
    folder = os.path.join(ROOT, "benchmarks", "results") if quick else os.path.join(ROOT, "docs", "appearance")
    suffix = "_quick" if quick else ""
    args.out = args.out or os.path.join(folder, f"brdf_vs_cycles{suffix}.json")
    args.plot = args.plot or os.path.join(folder, f"brdf_slices{suffix}.png")
    args.pairs = 4 if quick else 20
    args.translucent_pairs = 4 if quick else 20
    args.samples = 4 if quick else 16
    args.ref_samples = 0 if quick else 64
    args.bounces = 4
    args.slice_views = 13 if quick else 61
    args.slice_points = 3 if quick else 7
    args.speed_directions = 10 if quick else 100
    args.speed_cycles_pairs = 2 if quick else 6
    args.vb_settings = [("default", GonioSettings(directions=128, bounces=4, resolution=64, view_rays=128))]
    if not quick:
        args.vb_settings.append(("fine", GonioSettings(directions=256, bounces=4, resolution=64, view_rays=128)))

    def log(message):
        print(message, flush=True)

    started = time.perf_counter()
    command = " ".join([os.path.relpath(sys.argv[0], ROOT) if sys.argv[0] else "brdf_vs_cycles.py",
                        *(argv if argv is not None else sys.argv[1:])])
    if args.only == "translucent":
        return only_translucent(args, command, log, started)
    pairs = default_pairs(args.pairs)
    result = {
        "what": "tile BRDF (1/sr) of VisiBake's simulate_brdf against Cycles (benchmarks/brdf_reference.py)",
        "date": datetime.now(timezone.utc).isoformat(timespec="seconds"), "machine": _machine(),
        "command": command,
        "quick": quick, "units": "BRDF in 1/sr; times in wall seconds",
        "error_definition": "rel_rmse = sqrt(mean((vb - cy)^2)) / mean(cy) over the pairs, first channel; "
                            "cycles_rel_noise_rms = sqrt(mean(noise^2)) / mean(cy); rel_errors = vb / cy - 1",
        "pairs": pairs.tolist(), "target_rel_rmse": TARGET_RMSE,
        "pairs_theta_phi_deg": [[[math.degrees(math.acos(d[2])), math.degrees(math.atan2(d[1], d[0])) % 360]
                                 for d in pair] for pair in pairs],
    }
    result["kernel_warmup_s"] = warm_up()
    log(f"kernels loaded in {result['kernel_warmup_s']:.1f} s (outside every timing)")
    specs = tiles()
    result["accuracy"] = {name: accuracy(name, spec, pairs, args, log) for name, spec in specs.items()}
    result["translucent"] = translucent(args, log)
    result["translucent"].update({"date": result["date"], "command": command})
    result["direct_check"] = direct_check(pairs, args, log)
    slice_data = {}
    for name, spec in specs.items():
        slice_data[name] = slices(spec, args)
        slice_data[name]["title"] = {"vgroove": "V-groove (flat)", "woven": "woven (smooth)"}[name]
    result["slices"] = slice_data
    plot(slice_data, args.plot)
    log(f"wrote {args.plot} ({os.path.getsize(args.plot) / 1024:.0f} KB)")
    result["speed"] = speed(args, log)
    result["summary"] = {
        "accuracy": {name: {label: {"rel_rmse": entry["vs_cycles"]["rel_rmse"],
                                    "meets_target": entry["vs_cycles"]["rel_rmse"] <= TARGET_RMSE}
                            for label, entry in data["visibake"].items()}
                     for name, data in (*result["accuracy"].items(), ("translucent", result["translucent"]))},
        "speed_s": {label: result["speed"][label]["stats"]["wall_s"] for label in ("lambert", "glossy")},
    }
    result["total_s"] = round(time.perf_counter() - started, 1)
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as fh:
        json.dump(result, fh, indent=1)
    log(f"wrote {args.out} ({result['total_s']:.0f} s)")
    return 0


def only_translucent(args, command, log, started) -> int:
    """``--only translucent``: run that case and put it into the existing JSON (``--out``),
    every other key as it was (a missing file starts empty)."""
    result = {}
    if os.path.exists(args.out):
        with open(args.out) as fh:
            result = json.load(fh)
    warmup = warm_up()
    log(f"kernels loaded in {warmup:.1f} s (outside every timing)")
    entry = translucent(args, log)
    entry.update({"date": datetime.now(timezone.utc).isoformat(timespec="seconds"), "command": command,
                  "machine": _machine(), "kernel_warmup_s": warmup})
    result["translucent"] = entry
    summary = result.setdefault("summary", {}).setdefault("accuracy", {})
    summary["translucent"] = {label: {"rel_rmse": e["vs_cycles"]["rel_rmse"],
                                      "meets_target": e["vs_cycles"]["rel_rmse"] <= TARGET_RMSE}
                              for label, e in entry["visibake"].items()}
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as fh:
        json.dump(result, fh, indent=1)
    log(f"wrote {args.out} (translucent: {time.perf_counter() - started:.0f} s)")
    return 0


if __name__ == "__main__":
    status = main()
    from tools.blender_compat import compat  # bpy is loaded by now

    compat.end_module_process(status)
