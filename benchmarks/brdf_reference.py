"""Cycles as a virtual gonioreflectometer: the independent reference for tile BRDFs.

The paper's section 7.1 measures the BRDF of a periodic micro-geometry by rendering it.
This module does that with Cycles, in the current bpy session, for tiles of
``benchmarks/brdf_tiles.py`` (``positions, triangles, period``), and knows nothing of
VisiBake.

    from benchmarks.brdf_reference import cycles_brdf
    from benchmarks.brdf_tiles import v_groove_tile
    ref = cycles_brdf(*v_groove_tile(0.5), albedo=0.8, pairs=[(l, v), ...], samples=16)
    values, noise = ref            # (pairs, 3) each; ref.seed_values, ref.coverage, ...

Quantity and units
------------------
f(l, v) = L_mean / (E |cos theta_l|), in 1/sr, where E = 1 W/m^2 is the irradiance of the
sun on a plane perpendicular to it (a Cycles sun of strength 1 with angle 0), so
E |cos theta_l| is the irradiance on the macro plane z = const, and L_mean (W/m^2/sr) is
the outgoing radiance averaged over one period as seen along v (below). A flat white
Lambert tile gives 1/pi at every pair (tests/blender/test_brdf_reference.py checks this).

Light and view may lie on either side of the tile (z > 0: above, z < 0: below; not in its
plane): a sun along l with l_z < 0 shines on the tile's underside, a view with v_z < 0 is
a camera below looking up at the underside and at what the tile lets through. Then f is
the BSDF: reflection where l and v lie on one side, transmission where they lie on
opposite sides, normalised by |cos theta_l| as VisiBake's ``simulate_brdf`` does.

Scene
-----
The *central* copy of the tile is one object; all its neighbours, (2 nx + 1)(2 ny + 1) - 1
translated copies, are a second object that is a *holdout* (``Object.is_holdout``):
camera rays that hit a neighbour first end there with zero radiance and zero alpha,
but neighbours still cast shadows and reflect light for every other ray (Cycles applies
holdout only to camera rays). Checked with a "ridge" tile, the V-groove with its lattice
shifted by half a period so that every valley is split between two copies: direct
light matches the V-groove's closed form (shadowing and masking all come from the
holdout neighbours), and with 3 bounces ridge and groove agree within the noise
(inter-reflection between a copy and its holdout neighbours).

Both objects have the same material: a Diffuse BSDF of colour ``albedo`` (roughness 0:
Lambert), or with ``roughness`` given a Principled BSDF (base colour ``albedo``, that
roughness, default specular: IOR 1.5, Specular IOR Level 0.5). With ``transmission`` t > 0
(Lambert only) the material is a thin translucent sheet: Add Shader(Diffuse BSDF of colour
(1 - t) albedo, Translucent BSDF of colour t albedo), i.e. (1 - t) albedo / pi reflected
on the side the light arrives and t albedo / pi sent diffusely to the other side, the
thin-sheet model of ``core.appearance.gonio``. Flat shading (the triangles' own normals)
unless ``smooth``. The world is black (strength 0). The sun is along l (strength 1, angle
0: collimated, so direct light is noise-free), above or below the tile. An orthographic
camera looks along -v, from above or from below.

Faces are two-sided in Cycles: a ray that meets a face from behind shades it with the
normal flipped towards the ray (``SD_BACKFACING``), so the back of a face reflects like
its front. For a translucent tile that is VisiBake's model too (a translucent face's back
is a surface of its own, with the same material, its samples the twins of the front's).
For an opaque tile it is not (VisiBake's backs are black), but an opaque closed or
height-field tile seen and lit from above never shows a back.

How the period average is taken (and why it is exact)
-----------------------------------------------------
Let S_k be the set of points of the image plane whose camera ray first hits copy k.
Copy k is copy 0 translated by the lattice vector t_k, so S_k = S_0 + (the orthogonal
projection of t_k on the image plane), and the S_k (with the rays that hit nothing)
tile the image plane: S_0 is a fundamental domain of the projected lattice, whose
cell area is A_cell cos theta_v (A_cell = px * py). The radiance seen through a point is
periodic on that lattice, so its mean over one period as seen from v is

    L_mean = (integral of L over S_0) / (A_cell cos theta_v)

(rays through a pore that hit nothing add 0 to the integral and their area is part of
a fundamental domain: the formula holds for tiles with holes too). The holdout makes the
render *be* L restricted to S_0: the pixels of the central copy carry its radiance,
everything else is 0, and the pixels straddling the boundary of S_0 carry the
covered part exactly, because each camera sample is either in S_0 or not. With a
1-pixel box filter every sample stays in its pixel and pixels are disjoint squares of
side s, so ``sum(pixels) * s^2`` is an unbiased Monte Carlo estimate of the integral
(no pixel filter weights to normalise, no partition-of-unity error). The camera frames
the projection of the central copy's vertices with a 2-pixel border, so S_0 is entirely
in the image. The alpha channel gives the check ``coverage = sum(alpha) s^2 /
(A_cell cos theta_v)``, 1 for a tile with no holes.

Why not frame a whole number of periods without a mask: the camera footprint projected
on the plane is a parallelogram spanned by lattice vectors only if the view azimuth is a
lattice direction (a rational slope); the mask works at any azimuth.

Neighbours
----------
A camera ray into S_0 can be blocked by copies up to h tan theta_v away (h = the tile's
height: max z - min z); a shadow ray by copies up to h tan theta_l away. Bounced rays
leave in any direction; with ``max_angle`` (75 deg) as the grazing limit, a bounce hit
lies up to h tan(max_angle) away, and its own shadow ray again up to h tan theta_l.
``repeats=None`` uses nx = ceil(reach / px) + 1 (ny likewise) with
reach = max(h tan theta_l, h tan theta_v) + min(bounces, 2) h tan(max_angle) over all
pairs, theta the angle from the tile's normal on the direction's own side (arccos |z|:
a view or light below the tile is as oblique as its mirror image above), tangents of
angles above 89 deg taken at 89 deg. For the V-groove
(depth = period / 2) at 8 bounces that is 7 rings; with the same seeds, 14 rings change
the values by at most 0.01%, 4 rings by at most 0.11%, and 2 rings make them 0.06-0.7%
lower (light lost through the sides of the array).

Pixel sampling
--------------
Cycles (bpy 5.0.1, every sampling pattern) puts sample 0 of every pixel at the pixel
centre and only the later ones at random positions, so an N-sample render weights the
centre by 1/N: a 1-sample render of a flat tile seen at 75 deg gave a coverage of 1.104,
4 samples 1.019-1.025, 64 samples 1.001 (the truth is 1). The renders therefore use the
sample subset samples + 1 with offset 1 (``use_sample_subset``): samples 1..N only. Then
the mean coverage over 500 seeds is 1 within 0.3-1.5 standard errors at 1 and 2 samples
per pixel, for Tabulated Sobol, Sobol-Burley and blue noise alike. Persistent data is
off: with it, bpy 5.0.1 ignores a change of seed between renders.

Render settings (fixed)
-----------------------
Cycles on the CPU, ``samples`` per pixel, no adaptive sampling, no denoising, no light
tree threshold, clamping off (direct and indirect), Filter Glossy 0, reflective (and
refractive) caustics on, path guiding off, the Tabulated Sobol pattern, pixel filter BOX of width 1
px, film transparent, view transform Standard (look None, exposure 0, gamma 1), output
OPEN_EXR 32-bit float RGBA, read back linear with the OpenEXR package (bpy.data.images
where OpenEXR is missing); EXR RGB is premultiplied by alpha, i.e. exactly the covered
radiance.

Bounces: ``bounces`` = K sets Cycles' diffuse (and glossy) bounces and the total max
bounces to K. Cycles counts scattering events *after* the camera hit, and samples the
sun at every vertex: K = 0 gives direct light only (camera hit, shadow ray to the sun),
K = 1 adds light that reflected once before the surface seen, and so on: a path has at
most K + 1 surface vertices. This is checked: K = 0 on the V-groove matches the closed
form of direct light (``brdf_tiles.v_groove_direct_brdf``). With ``transmission`` > 0 the
transmission bounces are K too: Cycles counts a scattering through a Translucent BSDF (a
LABEL_TRANSMIT | LABEL_DIFFUSE closure) as a *transmission* bounce, not a diffuse one
(``path_state_next`` in Cycles' kernel), so with transmission bounces 0 every path that
crossed a sheet would end there; the total of K still caps a path at K + 1 surface
vertices of either kind, VisiBake's K bounces of reflected and transmitted light alike.

Noise
-----
Each pair is rendered ``len(seeds)`` times with independent seeds (at least 2); the value
is the mean. ``noise`` is the standard error of that mean from the *per-pixel* variance
across the seed renders: SE^2 = sum_p var_p / n (var_p the unbiased sample variance of
pixel p over the n renders), scaled like the value. Pixels are independent under
Tabulated Sobol (a per-pixel scramble), so this has as many degrees of freedom as there
are noisy pixels, unlike the spread of the n per-render values (``seed_noise``: their
sample standard deviation / sqrt(n), = half the difference of two), which has n - 1.
Both estimate the same thing (over 500 seeds of a flat tile at 1-2 samples, the per-pixel
estimate was 0.94-1.08 times the seeds' scatter with Tabulated Sobol and Sobol-Burley,
1.09-1.17 with blue noise); the per-pixel one is the stable one to build tolerances on.

Cost (2 cores, CPU): the V-groove (depth = period / 2, albedo 0.8, 15 x 15 copies) at
64 x 64 pixels and 2 seeds: 16 samples, 8 bounces, 0.15-0.4 s per pair, relative noise
0.07-0.6%.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import platform
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone

import bpy

import numpy as np
from mathutils import Vector

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)

__all__ = ["BrdfReference", "cycles_brdf", "default_pairs", "direction", "neighbour_rings", "main"]

SUN_STRENGTH = 1.0  # W/m^2 on a plane perpendicular to the sun (angle 0)
PAD_PIXELS = 2  # border around the central copy's projection, in pixels
MAX_TAN_ANGLE = 89.0  # degrees: cap for tan() in the neighbour count


@dataclass
class BrdfReference:
    """What :func:`cycles_brdf` measured. Unpacks as ``values, noise = result``.

    values : (pairs, 3) BRDF (1/sr), mean over the seed renders
    noise : (pairs, 3) standard error of ``values`` from the per-pixel variance across seeds
    seed_values : (seeds, pairs, 3) the BRDF of each seed render
    seed_noise : (pairs, 3) std(seed_values) / sqrt(seeds)
    coverage : (pairs,) area of the central copy's pixels (sum of alpha) / the projected
        cell area; 1 for a tile without holes, less where light passes through pores
    seconds : (pairs,) wall time of the renders of each pair (all seeds)
    settings : the render settings, the neighbour rings and the image sizes
    """

    values: np.ndarray
    noise: np.ndarray
    seed_values: np.ndarray
    seed_noise: np.ndarray
    coverage: np.ndarray
    seconds: np.ndarray
    settings: dict = field(default_factory=dict)

    def __iter__(self):
        return iter((self.values, self.noise))


def direction(theta_deg: float, phi_deg: float) -> np.ndarray:
    """Unit vector at zenith angle theta and azimuth phi (from +x towards +y), z up."""
    t, p = math.radians(theta_deg), math.radians(phi_deg)
    return np.array([math.sin(t) * math.cos(p), math.sin(t) * math.sin(p), math.cos(t)])


def default_pairs(count: int, max_theta: float = 75.0, seed: int = 0) -> np.ndarray:
    """``count`` (light, view) pairs, (count, 2, 3): four fixed ones first (normal/normal;
    theta_l 60 / theta_v 45 on opposite sides; the same on one side; 75 / 75 at azimuths
    90 deg apart), then pseudo-random ones (fixed seed), theta uniform in [0, max_theta],
    azimuth uniform."""
    fixed = [((0, 0), (0, 0)), ((60, 0), (45, 180)), ((60, 0), (45, 0)), ((max_theta, 0), (max_theta, 90))]
    rng = np.random.default_rng(seed)
    pairs = []
    for k in range(count):
        if k < len(fixed):
            (tl, pl), (tv, pv) = fixed[k]
        else:
            tl, tv = rng.uniform(0.0, max_theta, 2)
            pl, pv = rng.uniform(0.0, 360.0, 2)
        pairs.append((direction(tl, pl), direction(tv, pv)))
    return np.array(pairs, np.float64).reshape(-1, 2, 3)


def _tan(theta: float) -> float:
    return math.tan(min(theta, math.radians(MAX_TAN_ANGLE)))


def neighbour_rings(height: float, period, pairs, bounces: int, max_angle: float = 75.0) -> tuple[int, int]:
    """(nx, ny): rings of neighbour copies on each side of the central one (see the module doc)."""
    pairs = np.asarray(pairs, np.float64).reshape(-1, 2, 3)
    # the angle from the normal on the direction's own side: below the tile as above it
    thetas = np.arccos(np.clip(np.abs(pairs[:, :, 2]), 0.0, 1.0))
    reach = height * max(_tan(float(t)) for t in thetas.ravel())
    reach += min(int(bounces), 2) * height * _tan(math.radians(max_angle))
    px, py = np.asarray(period, np.float64).reshape(2)
    return int(math.ceil(reach / px)) + 1, int(math.ceil(reach / py)) + 1


# --------------------------------------------------------------------------- scene


def _mesh(name: str, positions: np.ndarray, triangles: np.ndarray, smooth: bool):
    mesh = bpy.data.meshes.new(name)
    mesh.vertices.add(len(positions))
    mesh.vertices.foreach_set("co", positions.astype(np.float32).ravel())
    mesh.loops.add(3 * len(triangles))
    mesh.loops.foreach_set("vertex_index", triangles.astype(np.int32).ravel())
    mesh.polygons.add(len(triangles))
    mesh.polygons.foreach_set("loop_start", np.arange(0, 3 * len(triangles), 3, dtype=np.int32))
    mesh.polygons.foreach_set("use_smooth", np.full(len(triangles), bool(smooth)))
    mesh.update(calc_edges=True)
    mesh.validate(verbose=False)
    return mesh


def _material(albedo, roughness, transmission: float = 0.0):
    from tools.blender_compat import compat

    material = bpy.data.materials.new("BRDF tile")
    tree = compat.ensure_node_tree(material)
    tree.nodes.clear()
    out = tree.nodes.new("ShaderNodeOutputMaterial")
    colour = (*[float(c) for c in albedo], 1.0)
    t = float(transmission)
    if t > 0.0:
        # a thin translucent sheet: (1 - t) albedo / pi reflected, t albedo / pi to the other side
        reflect = tree.nodes.new("ShaderNodeBsdfDiffuse")
        reflect.inputs["Color"].default_value = (*[(1.0 - t) * float(c) for c in albedo], 1.0)
        reflect.inputs["Roughness"].default_value = 0.0
        through = tree.nodes.new("ShaderNodeBsdfTranslucent")
        through.inputs["Color"].default_value = (*[t * float(c) for c in albedo], 1.0)
        add = tree.nodes.new("ShaderNodeAddShader")
        tree.links.new(reflect.outputs["BSDF"], add.inputs[0])
        tree.links.new(through.outputs["BSDF"], add.inputs[1])
        tree.links.new(add.outputs["Shader"], out.inputs["Surface"])
        return material
    if roughness is None:
        bsdf = tree.nodes.new("ShaderNodeBsdfDiffuse")
        bsdf.inputs["Color"].default_value = colour
        bsdf.inputs["Roughness"].default_value = 0.0
    else:
        bsdf = tree.nodes.new("ShaderNodeBsdfPrincipled")
        bsdf.inputs["Base Color"].default_value = colour
        bsdf.inputs["Roughness"].default_value = float(roughness)
    tree.links.new(bsdf.outputs["BSDF"], out.inputs["Surface"])
    return material


def _settings(scene, samples: int, bounces: int, path: str, transmission_bounces: int = 0) -> None:
    scene.render.engine = "CYCLES"
    cycles = scene.cycles
    cycles.device = "CPU"
    # Sample 0 of every pixel is at the pixel centre (see "Pixel sampling" in the module
    # doc): render samples 1..samples of samples + 1, i.e. skip it.
    cycles.samples = int(samples) + 1
    cycles.use_sample_subset = True
    cycles.sample_offset = 1
    cycles.sample_subset_length = int(samples)
    cycles.use_adaptive_sampling = False
    cycles.use_denoising = False
    cycles.use_animated_seed = False
    cycles.sample_clamp_direct = 0.0
    cycles.sample_clamp_indirect = 0.0
    cycles.light_sampling_threshold = 0.0
    cycles.blur_glossy = 0.0
    cycles.caustics_reflective = True
    cycles.caustics_refractive = True
    cycles.use_guiding = False
    try:
        cycles.sampling_pattern = "TABULATED_SOBOL"
    except TypeError:  # pragma: no cover - a Cycles without it keeps its default
        pass
    cycles.pixel_filter_type = "BOX"
    cycles.filter_width = 1.0
    cycles.max_bounces = int(bounces)
    cycles.diffuse_bounces = int(bounces)
    cycles.glossy_bounces = int(bounces)
    # a Translucent BSDF scatters as a transmission bounce (see "Bounces" in the module doc)
    cycles.transmission_bounces = int(transmission_bounces)
    cycles.volume_bounces = 0
    cycles.transparent_max_bounces = 0
    cycles.min_light_bounces = 0
    cycles.min_transparent_bounces = 0
    render = scene.render
    render.film_transparent = True
    render.resolution_percentage = 100
    render.pixel_aspect_x = render.pixel_aspect_y = 1.0
    render.use_compositing = False
    render.use_sequencer = False
    render.use_persistent_data = False  # with it, a change of seed is ignored (bpy 5.0.1)
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    scene.view_settings.exposure = 0.0
    scene.view_settings.gamma = 1.0
    image = render.image_settings
    image.file_format = "OPEN_EXR"
    image.color_mode = "RGBA"
    image.color_depth = "32"
    image.exr_codec = "ZIP"
    render.filepath = path


def _read_exr(path: str, width: int, height: int) -> np.ndarray:
    """(height, width, 4) float64 RGBA as written (linear, premultiplied); row order does
    not matter here (only sums are taken)."""
    try:
        import OpenEXR
    except ImportError:  # pragma: no cover - the venv has it (requirements.txt)
        image = bpy.data.images.load(path, check_existing=False)
        try:
            pixels = np.empty(width * height * 4, np.float32)
            image.pixels.foreach_get(pixels)
        finally:
            bpy.data.images.remove(image)
        return pixels.reshape(height, width, 4).astype(np.float64)
    with OpenEXR.File(path) as exr:
        channels = exr.channels()
        if "RGBA" in channels:
            pixels = np.asarray(channels["RGBA"].pixels, np.float64)
        else:
            pixels = np.stack([np.asarray(channels[c].pixels, np.float64) for c in "RGBA"], -1)
    assert pixels.shape == (height, width, 4), (pixels.shape, width, height)
    return pixels


def _frame(camera_obj, camera, centre_positions: np.ndarray, all_corners: np.ndarray, v: np.ndarray,
           resolution: int, scene) -> float:
    """Point the orthographic camera along -v, framing the central copy with a border of
    PAD_PIXELS; set the image size; return the pixel side s. Everything is measured along v
    and across it, so a view from below (v_z < 0: the camera below the tile, looking up)
    is framed as one from above."""
    camera_obj.rotation_mode = "QUATERNION"
    camera_obj.rotation_quaternion = Vector(v.tolist()).to_track_quat("Z", "Y")
    rot = np.array(camera_obj.rotation_quaternion.to_matrix(), np.float64)
    right, up = rot[:, 0], rot[:, 1]
    r = centre_positions @ right
    u = centre_positions @ up
    width, height = float(r.max() - r.min()), float(u.max() - u.min())
    inner = max(int(resolution) - 2 * PAD_PIXELS, 1)
    s = max(width, height, 1e-9) / inner
    rx = max(int(math.ceil(width / s - 1e-9)), 1) + 2 * PAD_PIXELS
    ry = max(int(math.ceil(height / s - 1e-9)), 1) + 2 * PAD_PIXELS
    scene.render.resolution_x, scene.render.resolution_y = rx, ry
    camera.type = "ORTHO"
    camera.sensor_fit = "AUTO"
    camera.ortho_scale = max(rx, ry) * s
    camera.shift_x = camera.shift_y = 0.0
    # beyond every copy along v (above the array, or below it for a view from below): the
    # camera plane is where camera rays start
    top = float((all_corners @ v).max())
    low = float((all_corners @ v).min())
    rc, uc = 0.5 * (r.max() + r.min()), 0.5 * (u.max() + u.min())
    distance = top + 1.0 + (top - low)
    camera_obj.location = (rc * right + uc * up + distance * v).tolist()
    camera.clip_start = 1e-3
    camera.clip_end = 2.0 * (distance - low) + 10.0
    return s


def cycles_brdf(positions, triangles, period, albedo, pairs, samples: int = 64, repeats=None,
                resolution: int = 64, roughness: float | None = None, bounces: int = 0, seeds=(1, 2),
                smooth: bool = False, max_angle: float = 75.0, workdir: str | None = None,
                keep_scene: bool = False, transmission: float = 0.0) -> BrdfReference:
    """The BRDF of a periodic tile at each (light, view) pair, rendered by Cycles.

    positions, triangles, period : a tile of benchmarks/brdf_tiles.py (one period in
        [0, px] x [0, py], z up)
    albedo : float or RGB
    pairs : (n, 2, 3) or a sequence of (l, v): unit vectors towards the light and the
        viewer, z up (they are normalised), above (z > 0) or below (z < 0) the tile but
        not in its plane: below, the sun shines on the underside / the camera looks up
    samples : Cycles samples per pixel per seed render
    repeats : rings of neighbour copies on each side, int or (nx, ny); None computes them
        from the tile height and the angles (:func:`neighbour_rings`)
    resolution : pixels along the longer side of the image of the central copy
    roughness : None for a Diffuse BSDF (Lambert), else a Principled BSDF of that roughness
    bounces : Cycles diffuse (and glossy) bounces K: 0 = direct light only
    seeds : the Cycles seeds of the independent renders (>= 2 for a noise estimate)
    smooth : smooth shading (vertex normals) instead of the flat triangles
    workdir : where the EXRs go (a temporary folder, removed, when None)
    keep_scene : leave the scene (named "BRDF reference") in bpy.data, e.g. to inspect it
    transmission : t in [0, 1], the share of the diffuse light a face passes to its other
        side (a thin translucent sheet: Diffuse (1 - t) albedo + Translucent t albedo);
        Lambert only (not with ``roughness``)

    The renders happen in a new scene of the current session; the session's own scenes,
    objects and settings are not touched (the new scene and its data are removed after,
    unless keep_scene). See the module doc for the period average, units and noise.
    """
    positions = np.asarray(positions, np.float64)
    triangles = np.asarray(triangles, np.int32)
    period = np.asarray(period, np.float64).reshape(2)
    albedo = np.broadcast_to(np.asarray(albedo, np.float64), (3,))
    pairs = np.asarray(pairs, np.float64).reshape(-1, 2, 3)
    pairs = pairs / np.linalg.norm(pairs, axis=2, keepdims=True)
    if (np.abs(pairs[:, :, 2]) <= 1e-6).any():
        raise ValueError("light and view directions must not lie in the tile's plane (|z| > 1e-6)")
    transmission = float(transmission)
    if not 0.0 <= transmission <= 1.0:
        raise ValueError(f"transmission must lie in [0, 1], got {transmission}")
    if transmission > 0.0 and roughness is not None:
        raise ValueError("transmission is for the Lambert material only (roughness None)")
    seeds = [int(s) for s in seeds]
    if len(seeds) < 2:
        raise ValueError("at least two seeds are needed for a noise estimate")
    height = float(positions[:, 2].max() - positions[:, 2].min())
    if repeats is None:
        nx, ny = neighbour_rings(height, period, pairs, bounces, max_angle)
    else:
        nx, ny = np.broadcast_to(np.asarray(repeats, int), (2,)).tolist()

    # the neighbours: every lattice translate but the central one, as one mesh
    offsets = [(i * period[0], j * period[1], 0.0) for i in range(-nx, nx + 1) for j in range(-ny, ny + 1)
               if (i, j) != (0, 0)]
    offsets = np.array(offsets, np.float64).reshape(-1, 3)
    n_vert = len(positions)
    ring_positions = (positions[None, :, :] + offsets[:, None, :]).reshape(-1, 3)
    ring_triangles = (triangles[None, :, :] + n_vert * np.arange(len(offsets))[:, None, None]).reshape(-1, 3)
    lo, hi = ring_positions.min(0), ring_positions.max(0)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])

    own_dir = workdir is None
    workdir = tempfile.mkdtemp(prefix="visibake-brdf-") if own_dir else workdir
    os.makedirs(workdir, exist_ok=True)
    scene = bpy.data.scenes.new("BRDF reference")
    created = {"meshes": [], "objects": [], "materials": [], "lights": [], "cameras": [], "worlds": []}
    try:
        material = _material(albedo, roughness, transmission)
        created["materials"].append(material)
        for name, pos, tri, holdout in (("BRDF centre", positions, triangles, False),
                                        ("BRDF neighbours", ring_positions, ring_triangles, True)):
            mesh = _mesh(name, pos, tri, smooth)
            mesh.materials.append(material)
            obj = bpy.data.objects.new(name, mesh)
            obj.is_holdout = holdout
            if hasattr(obj, "shadow_terminator_geometry_offset"):  # not in every Blender's bpy
                obj.shadow_terminator_geometry_offset = 0.0
            scene.collection.objects.link(obj)
            created["meshes"].append(mesh)
            created["objects"].append(obj)
        world = bpy.data.worlds.new("BRDF black")
        from tools.blender_compat import compat

        world_tree = compat.ensure_node_tree(world)
        world.color = (0.0, 0.0, 0.0)
        if world_tree is not None:
            for node in world_tree.nodes:
                if node.type == "BACKGROUND":
                    node.inputs["Color"].default_value = (0.0, 0.0, 0.0, 1.0)
                    node.inputs["Strength"].default_value = 0.0
        scene.world = world
        created["worlds"].append(world)
        light = bpy.data.lights.new("BRDF sun", "SUN")
        light.energy = SUN_STRENGTH
        light.angle = 0.0
        sun = bpy.data.objects.new("BRDF sun", light)
        sun.rotation_mode = "QUATERNION"
        scene.collection.objects.link(sun)
        camera = bpy.data.cameras.new("BRDF camera")
        camera_obj = bpy.data.objects.new("BRDF camera", camera)
        scene.collection.objects.link(camera_obj)
        scene.camera = camera_obj
        created["lights"].append(light)
        created["cameras"].append(camera)
        created["objects"] += [sun, camera_obj]

        cell = float(period[0] * period[1])
        n_pairs = len(pairs)
        seed_values = np.zeros((len(seeds), n_pairs, 3))
        noise = np.zeros((n_pairs, 3))
        coverage = np.zeros(n_pairs)
        seconds = np.zeros(n_pairs)
        sizes = []
        for k, (l, v) in enumerate(pairs):
            sun.rotation_quaternion = Vector(l.tolist()).to_track_quat("Z", "Y")
            path = os.path.join(workdir, f"pair{k:03d}.exr")
            _settings(scene, samples, bounces, path, bounces if transmission > 0.0 else 0)
            s = _frame(camera_obj, camera, positions, corners, v, resolution, scene)
            rx, ry = scene.render.resolution_x, scene.render.resolution_y
            sizes.append((rx, ry))
            # radiance integral over S_0 -> L_mean -> f (|cos|: either side of the tile)
            scale = s * s / (cell * abs(v[2])) / (SUN_STRENGTH * abs(l[2]))
            images = []
            start = time.perf_counter()
            for m, seed in enumerate(seeds):
                scene.cycles.seed = seed
                bpy.ops.render.render(write_still=True, scene=scene.name)
                pixels = _read_exr(path, rx, ry)
                images.append(pixels)
                seed_values[m, k] = pixels[..., :3].sum((0, 1)) * scale
            seconds[k] = time.perf_counter() - start
            stack = np.stack(images)  # (n, H, W, 4)
            n = len(seeds)
            var = stack[..., :3].var(axis=0, ddof=1)  # per pixel, per channel
            noise[k] = np.sqrt(var.sum((0, 1)) / n) * scale
            coverage[k] = stack[..., 3].mean(0).sum() * s * s / (cell * abs(v[2]))
        values = seed_values.mean(0)
        seed_noise = seed_values.std(0, ddof=1) / math.sqrt(len(seeds))
        settings = {
            "samples": int(samples), "seeds": seeds, "bounces": int(bounces), "resolution": int(resolution),
            "image_sizes": sizes, "repeats": [int(nx), int(ny)], "tile_height": height,
            "tile_triangles": int(len(triangles)), "albedo": albedo.tolist(),
            "material": (f"Add Shader(Diffuse BSDF {1.0 - transmission:g} x albedo, Translucent BSDF "
                         f"{transmission:g} x albedo)") if transmission > 0.0
            else "Diffuse BSDF (roughness 0)" if roughness is None
            else f"Principled BSDF (roughness {roughness}, Specular IOR Level 0.5, IOR 1.5)",
            "transmission": transmission, "transmission_bounces": int(bounces) if transmission > 0.0 else 0,
            "smooth": bool(smooth), "max_angle": float(max_angle), "sun_strength": SUN_STRENGTH,
            "pixel_filter": "BOX, 1 px", "sampling_pattern": scene.cycles.sampling_pattern,
            "noise": "standard error of the mean over seeds, from the per-pixel variance",
            "blender": bpy.app.version_string,
        }
        return BrdfReference(values, noise, seed_values, seed_noise, coverage, seconds, settings)
    finally:
        if not keep_scene:
            bpy.data.scenes.remove(scene)
            for kind in ("objects", "meshes", "materials", "lights", "cameras", "worlds"):
                collection = getattr(bpy.data, kind)
                for datablock in created[kind]:
                    collection.remove(datablock)
        if own_dir:
            shutil.rmtree(workdir, ignore_errors=True)


# --------------------------------------------------------------------------- CLI


def _tile(name: str, args):
    from benchmarks import brdf_tiles

    if name == "flat":
        return brdf_tiles.flat_tile()
    if name == "vgroove":
        return brdf_tiles.v_groove_tile(args.depth)
    if name == "woven":
        return brdf_tiles.woven_tile()
    if name == "heightfield":
        rng = np.random.default_rng(0)
        n = 16
        # a smooth random periodic field: low frequencies of white noise
        spectrum = np.fft.fft2(rng.standard_normal((n, n)))
        k = np.fft.fftfreq(n) * n
        spectrum *= (np.hypot(*np.meshgrid(k, k)) <= 3)
        field_ = np.fft.ifft2(spectrum).real
        return brdf_tiles.heightfield_tile(args.depth * (field_ - field_.min()) / np.ptp(field_))
    raise ValueError(name)


def _machine() -> dict:
    info = {"node": platform.node(), "system": platform.platform(), "processor": platform.processor(),
            "cpus": os.cpu_count(), "python": platform.python_version(), "blender": bpy.app.version_string}
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    info["cpu"] = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return info


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tile", choices=("flat", "vgroove", "woven", "heightfield"), default="flat")
    parser.add_argument("--pairs", type=int, default=20, help="number of (light, view) pairs (default_pairs)")
    parser.add_argument("--max-theta", type=float, default=75.0, help="largest zenith angle of the pairs (deg)")
    parser.add_argument("--samples", type=int, default=64)
    parser.add_argument("--seeds", type=int, default=2, help="independent renders per pair (>= 2)")
    parser.add_argument("--resolution", type=int, default=64)
    parser.add_argument("--bounces", type=int, default=0, help="Cycles diffuse bounces (0 = direct only)")
    parser.add_argument("--albedo", type=float, nargs="+", default=[0.8])
    parser.add_argument("--roughness", type=float, default=None, help="Principled BSDF with this roughness")
    parser.add_argument("--transmission", type=float, default=0.0,
                        help="a thin translucent sheet: this share of the diffuse light to the other side")
    parser.add_argument("--depth", type=float, default=0.5, help="V-groove depth / heightfield amplitude")
    parser.add_argument("--repeats", type=int, default=None, help="neighbour rings (default: computed)")
    parser.add_argument("--out", required=True, help="JSON file to write")
    args = parser.parse_args(argv)
    albedo = args.albedo[0] if len(args.albedo) == 1 else args.albedo
    positions, triangles, period = _tile(args.tile, args)
    pairs = default_pairs(args.pairs, args.max_theta)
    start = time.perf_counter()
    ref = cycles_brdf(positions, triangles, period, albedo, pairs, samples=args.samples,
                      repeats=args.repeats, resolution=args.resolution, roughness=args.roughness,
                      bounces=args.bounces, seeds=range(1, args.seeds + 1), transmission=args.transmission)
    total = time.perf_counter() - start
    result = {
        "tile": args.tile, "depth": args.depth if args.tile in ("vgroove", "heightfield") else None,
        "period": period.tolist(), "pairs": pairs.tolist(), "values": ref.values.tolist(),
        "noise": ref.noise.tolist(), "seed_values": ref.seed_values.tolist(),
        "seed_noise": ref.seed_noise.tolist(), "coverage": ref.coverage.tolist(),
        "seconds": ref.seconds.tolist(), "total_seconds": total, "settings": ref.settings,
        "machine": _machine(), "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "units": "BRDF in 1/sr: mean radiance over one period / (sun irradiance * cos theta_l)",
    }
    if args.tile == "vgroove" and args.bounces == 0 and args.roughness is None and args.transmission == 0.0:
        from benchmarks.brdf_tiles import v_groove_direct_brdf

        result["analytic_direct"] = [np.broadcast_to(v_groove_direct_brdf(args.depth, albedo, l, v), (3,)).tolist()
                                     for l, v in pairs]
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as fh:
        json.dump(result, fh, indent=1)
    for k, (l, v) in enumerate(pairs):
        print(f"pair {k:2d} l={np.round(l, 3)} v={np.round(v, 3)}  f={ref.values[k, 0]:.5f} "
              f"+- {ref.noise[k, 0]:.5f}  coverage {ref.coverage[k]:.4f}  {ref.seconds[k]:.1f} s")
    print(f"wrote {args.out} ({total:.1f} s)")
    return 0


if __name__ == "__main__":
    status = main()
    from tools.blender_compat import compat  # bpy is loaded by now

    compat.end_module_process(status)
