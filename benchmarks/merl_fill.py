"""How well core.appearance.merl.fill_from_samples fills a MERL table from L x V simulated
pairs, by the choice of the light and view sets (and of the fill's kernel along phi_d).

    NUMBA_CACHE_DIR=/tmp/numba-merl .venv/bin/python benchmarks/merl_fill.py
        [--lights 100] [--views 100] [--seeds 3] [--json docs/appearance/merl_fill.json]

(about 1.5 minutes on 2 shared cores: 30 fills of ~2 s and their lookups)

Analytic BRDFs stand in for the simulator: each is sampled on the grid of every light and
view, filled into a table, and the table looked up (merl.evaluate, nearest cell) against the
BRDF. The error is the relative RMS error over lookups in cells with data:

- all: 20,000 pairs uniform in solid angle (light and view independently);
- peak / mid / wide: 4,000 pairs uniform in the table's cell-index space with theta_h index
  < 20 (theta_h < 4.4 degrees: the specular peak), 20-44, >= 45;
- grazing: 4,000 pairs uniform in cell-index space with theta_d index >= 70 (theta_d > 70
  degrees), any theta_h.

The sets compared, at the same pair count:

- fibonacci, old fill: gonio.hemisphere_directions(L) x gonio.hemisphere_directions(V) (the
  same set twice when L = V), what the BRDF job used, filled as before phi_arc_row existed
  (phi_arc_row=None, min_weight=6);
- fibonacci: the same sets, today's fill (merl's defaults);
- merl sets, old fill: merl.merl_direction_sets(L, V), phi_arc_row=None, min_weight=6;
- merl sets: merl.merl_direction_sets(L, V), today's fill;
- floor: a table of the exact values at the cell centres (what nearest-cell lookup costs).

With --seeds N > 1 the merl sets are also drawn with seeds 1..N-1 and the table reports
their mean and spread. The BRDFs: Lambert (must fill exactly), Lambert + normalised
Blinn-Phong 50, GGX alpha 0.2 and 0.5 (Schlick Fresnel, separable Smith masking) + Lambert,
two BRDFs that depend on phi_d away from the peak, which a kernel too long along phi_d
would blur: Oren-Nayar sigma 0.5 and Minnaert k 0.7 (a dark rough surface); and an
anisotropic one, Lambert + Blinn-Phong 50 times (1 + 0.5 cos 2 phi_h), against its phi_h
average (Lambert + Blinn-Phong 50): the table averages the samples' phi_h, and how many
different ones a cell's kernel gathers shows here, as it would with noisy samples.
"""
import argparse
import datetime
import json
import os
import platform
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from core.appearance import gonio, merl  # noqa: E402

DIFFUSE = np.array([0.3, 0.4, 0.5])
SPECULAR = np.array([0.1, 0.2, 0.3])
BANDS = ("all", "peak", "mid", "wide", "grazing")


def _half_vectors(light, view):
    h = light + view
    return h / np.linalg.norm(h, axis=1, keepdims=True)


def lambert(light, view):
    """(K, 3) 1/sr: DIFFUSE / pi."""
    return np.tile(DIFFUSE / np.pi, (len(light), 1))


def blinn_phong(exponent):
    """Lambert plus normalised Blinn-Phong in cos(theta_h), as tests/core/test_merl.py."""
    def brdf(light, view):
        lobe = (exponent + 2) / (2 * np.pi) * np.clip(_half_vectors(light, view)[:, 2], 0.0, 1.0) ** exponent
        return DIFFUSE / np.pi + SPECULAR * lobe[:, None]
    return brdf


def ggx(alpha):
    """Lambert plus GGX of roughness ``alpha``, Schlick Fresnel from F0 = SPECULAR, separable
    Smith masking: (K, 3) 1/sr."""
    a2 = alpha * alpha

    def smith(cosine):
        return 2.0 * cosine / (cosine + np.sqrt(a2 + (1.0 - a2) * cosine * cosine))

    def brdf(light, view):
        h = _half_vectors(light, view)
        distribution = a2 / (np.pi * (h[:, 2] ** 2 * (a2 - 1.0) + 1.0) ** 2)
        cos_d = np.clip(np.einsum("ij,ij->i", light, h), 0.0, 1.0)
        fresnel = SPECULAR + (1.0 - SPECULAR) * ((1.0 - cos_d) ** 5)[:, None]
        cl, cv = light[:, 2], view[:, 2]
        lobe = distribution * smith(cl) * smith(cv) / (4.0 * cl * cv)
        return DIFFUSE / np.pi + lobe[:, None] * fresnel
    return brdf


def oren_nayar(sigma):
    """Oren-Nayar (the qualitative model) of roughness ``sigma`` radians: (K, 3) 1/sr."""
    s2 = sigma * sigma
    a, b = 1.0 - 0.5 * s2 / (s2 + 0.33), 0.45 * s2 / (s2 + 0.09)

    def brdf(light, view):
        ti, to = np.arccos(np.clip(light[:, 2], -1, 1)), np.arccos(np.clip(view[:, 2], -1, 1))
        relative = np.arctan2(light[:, 1], light[:, 0]) - np.arctan2(view[:, 1], view[:, 0])
        factor = a + b * np.maximum(0.0, np.cos(relative)) * np.sin(np.maximum(ti, to)) * np.tan(np.minimum(ti, to))
        return DIFFUSE / np.pi * factor[:, None]
    return brdf


def minnaert(k):
    """Minnaert: DIFFUSE / pi * (cos theta_l cos theta_v)^(k - 1), (K, 3) 1/sr."""
    def brdf(light, view):
        return DIFFUSE / np.pi * ((light[:, 2] * view[:, 2]) ** (k - 1.0))[:, None]
    return brdf


def anisotropic(brdf):
    """``brdf`` times 1 + 0.5 cos(2 phi_h): (K, 3) 1/sr. Its phi_h average is ``brdf``."""
    def sampled(light, view):
        _, phi_h, _, _ = merl.half_difference(light, view)
        return brdf(light, view) * (1.0 + 0.5 * np.cos(2.0 * phi_h))[:, None]
    return sampled


BRDFS = {
    "Lambert": lambert,
    "Lambert + Blinn-Phong 50": blinn_phong(50),
    "GGX 0.2 + Lambert": ggx(0.2),
    "GGX 0.5 + Lambert": ggx(0.5),
    "Oren-Nayar 0.5": oren_nayar(0.5),
    "Minnaert 0.7": minnaert(0.7),
    "Phong 50 x (1+cos 2phi_h)/2": blinn_phong(50),
}
# What the fill is given, where it is not the BRDF the table is checked against.
SAMPLED = {"Phong 50 x (1+cos 2phi_h)/2": anisotropic(blinn_phong(50))}
OLD_FILL = {"phi_arc_row": None, "min_weight": 6.0}
NEW_FILL = {"phi_arc_row": merl.FILL_PHI_ARC_ROW, "min_weight": merl.FILL_MIN_WEIGHT}


def _uniform_pairs(count, seed):
    """(count, 3) light and view, each uniform in solid angle above the horizon."""
    rng = np.random.default_rng(seed)

    def hemisphere():
        z = rng.uniform(0.0, 1.0, count)
        phi = rng.uniform(0.0, 2.0 * np.pi, count)
        r = np.sqrt(1.0 - z * z)
        return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])
    return hemisphere(), hemisphere()


def _index_space_pairs(count, seed, theta_h_rows=(0.0, 90.0), theta_d_rows=(0.0, 90.0)):
    """(count, 3) light and view uniform in the table's cell-index space within the given
    theta_h and theta_d index ranges, random phi_h, kept where the cell has data."""
    rng = np.random.default_rng(seed)
    valid = merl.valid_cells().ravel()
    lights, views, kept = [], [], 0
    while kept < count:
        n = 4 * count
        theta_h = (rng.uniform(*theta_h_rows, n) / 90.0) ** 2 * (np.pi / 2)
        theta_d = rng.uniform(*theta_d_rows, n) / 90.0 * (np.pi / 2)
        phi_d = rng.uniform(0.0, np.pi, n)
        light, view = merl.direction_pair(theta_h, theta_d, phi_d, rng.uniform(-np.pi, np.pi, n))
        keep = valid[merl.cell_index(theta_h, theta_d, phi_d)] & (light[:, 2] > 0) & (view[:, 2] > 0)
        lights.append(light[keep])
        views.append(view[keep])
        kept += int(keep.sum())
    return np.concatenate(lights)[:count], np.concatenate(views)[:count]


def evaluation_pairs():
    """{band: (light, view)}: where the tables are looked up (see the module's docstring)."""
    return {"all": _uniform_pairs(20000, 1),
            "peak": _index_space_pairs(4000, 2, theta_h_rows=(0.0, 20.0)),
            "mid": _index_space_pairs(4000, 3, theta_h_rows=(20.0, 45.0)),
            "wide": _index_space_pairs(4000, 4, theta_h_rows=(45.0, 90.0)),
            "grazing": _index_space_pairs(4000, 5, theta_d_rows=(70.0, 90.0))}


def relative_rmse(table, brdf, light, view):
    """Relative RMS error of the table's lookup against ``brdf`` over the pairs whose cell
    has data."""
    theta_h, _, theta_d, phi_d = merl.half_difference(light, view)
    has_data = merl.valid_cells().ravel()[merl.cell_index(theta_h, theta_d, phi_d)]
    truth = brdf(light, view)[has_data]
    error = (merl.evaluate(table, light[has_data], view[has_data]) - truth) / truth
    return float(np.sqrt(np.mean(error ** 2)))


def exact_table(brdf):
    """(3, 90, 90, 180): the BRDF at every cell centre with data, NO_DATA elsewhere."""
    light, view = merl.direction_pair(*merl.cell_centres())
    above = (light[:, 2] > 0) & (view[:, 2] > 0)
    table = np.full((3, merl.CELLS), merl.NO_DATA)
    table[:, above] = brdf(light[above], view[above]).T
    return table.reshape(merl.TABLE_SHAPE)


def filled_table(brdf, lights, views, fill):
    """The table filled (``fill``: fill_from_samples' keywords) from every pair of ``lights``
    x ``views``, and the seconds it took."""
    pair_light = np.repeat(lights, len(views), axis=0)
    pair_view = np.tile(views, (len(lights), 1))
    started = time.perf_counter()
    table = merl.fill_from_samples(pair_light, pair_view, brdf(pair_light, pair_view), **fill)
    return table, time.perf_counter() - started


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--lights", type=int, default=100)
    parser.add_argument("--views", type=int, default=100)
    parser.add_argument("--seeds", type=int, default=3, help="merl sets drawn with seeds 0..N-1")
    parser.add_argument("--json", default=os.path.join(ROOT, "docs", "appearance", "merl_fill.json"))
    options = parser.parse_args()
    pairs = evaluation_pairs()
    fibonacci = (gonio.hemisphere_directions(options.lights), gonio.hemisphere_directions(options.views))
    seeded = [merl.merl_direction_sets(options.lights, options.views, seed) for seed in range(options.seeds)]
    configurations = {
        "fibonacci, old fill": ([fibonacci], OLD_FILL),
        "fibonacci": ([fibonacci], NEW_FILL),
        "merl sets, old fill": (seeded[:1], OLD_FILL),
        "merl sets": (seeded, NEW_FILL),
    }
    results, fill_seconds = {}, []
    header = f"{'BRDF':28s} {'sets':22s} " + " ".join(f"{band:>13s}" for band in BANDS)
    print(f"relative RMSE of merl.evaluate, {options.lights} x {options.views} pairs", flush=True)
    print(header, flush=True)
    for name, brdf in BRDFS.items():
        results[name] = {}
        for label, (sets, fill) in configurations.items():
            scores = []
            for lights, views in sets:
                table, seconds = filled_table(SAMPLED.get(name, brdf), lights, views, fill)
                fill_seconds.append(seconds)
                scores.append([relative_rmse(table, brdf, *pairs[band]) for band in BANDS])
            scores = np.array(scores)
            mean, spread = scores.mean(axis=0), scores.std(axis=0)
            results[name][label] = {band: round(float(m), 4) for band, m in zip(BANDS, mean)}
            if len(sets) > 1:
                results[name][label]["spread"] = {band: round(float(s), 4) for band, s in zip(BANDS, spread)}
            cells = [f"{m:.3f}" + (f"+-{s:.3f}" if len(sets) > 1 else "") for m, s in zip(mean, spread)]
            print(f"{name:28s} {label:22s} " + " ".join(f"{c:>13s}" for c in cells), flush=True)
        floor = exact_table(brdf)
        results[name]["floor"] = {band: round(relative_rmse(floor, brdf, *pairs[band]), 4) for band in BANDS}
        print(f"{name:28s} {'floor':22s} " + " ".join(f"{results[name]['floor'][band]:13.3f}" for band in BANDS),
              flush=True)
    record = {
        "benchmark": "merl_fill",
        "date": datetime.datetime.now().isoformat(timespec="seconds"),
        "machine": {"platform": platform.platform(), "processor": platform.processor(), "cpus": os.cpu_count()},
        "lights": options.lights, "views": options.views, "seeds": options.seeds,
        "fill": {"new": NEW_FILL, "old": OLD_FILL, "aspect": merl.FILL_ASPECT,
                 "seconds_median": round(float(np.median(fill_seconds)), 2)},
        "sets": {"view_min_z": merl.VIEW_MIN_Z, "extra_partner_share": merl.EXTRA_PARTNER_SHARE,
                 "partner_theta_h_rows": merl.PARTNER_THETA_H_ROWS},
        "metric": "relative RMSE of merl.evaluate against the BRDF, cells with data; all: 20,000 pairs uniform "
                  "in solid angle; peak/mid/wide: 4,000 pairs uniform in cell-index space, theta_h index <20, "
                  "20-44, >=45; grazing: theta_d index >= 70",
        "results": results,
    }
    if options.json:
        os.makedirs(os.path.dirname(options.json), exist_ok=True)
        with open(options.json, "w") as handle:
            json.dump(record, handle, indent=1)
        print(f"written {options.json}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
