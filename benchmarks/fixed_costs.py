"""The passes a bake runs once per preparation (or once per lamp), compiled against their
numpy fallbacks, in one process: the same inputs, both paths timed back to back, results
checked bitwise equal.

- On ``benchmarks.scenes.dense_mesh`` (201k triangles on a 64^2 atlas): the UV rasteriser
  (core.sampling.raster), once at the atlas's size and once at 2048^2; the UV layout's check
  (core.sampling.atlas.uv_layout_stats) and the face normals and areas (core.geometry); the
  loop triangles' vertex and material indices read through the attributes
  (operators.adapter.extract.read_triangles) against ``loop_triangles.foreach_get``; and
  embree's copy of the mesh (core.visibility.rays._triangle_mesh) against embreex's own
  ``TriangleMesh`` on the numpy arrays (the same buffers: not compared bit by bit, "n/a"), and
  the mesh handed to embree where it lies (core.visibility.embree_shared) against that copy.
- On the demo scene (403k texels, 128 directions, interleaved): the contact and near-field
  passes (core.transport.contacts: close_entries, exposed_share, _texel_owners;
  core.transport.interleave.filter_pairs) and, for each hard lamp, the direct light with the
  samples that need no shadow ray summed in one pass (LampPoints.add_untraced) against the
  point-by-point loop, and the set-up of the shadow rays of its first corner probe
  (core.transport.direct.shadow_rays).

Each figure is the median of ``--repeats`` calls after one unmeasured call; ``compiled_seconds``
is VisiBake's own path (compiled, or for the reads and embree's copy, what it does instead). Writes
``benchmarks/results/fixed_costs.json`` with the machine, settings and date.

    .venv/bin/python benchmarks/fixed_costs.py [--repeats 3]
"""
import argparse
import importlib
import os
import statistics
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)


def timed(function, repeats: int = 3):
    """(median seconds of ``repeats`` calls after a first unmeasured one, the last result)."""
    result = function()
    seconds = []
    for _ in range(repeats):
        started = time.perf_counter()
        result = function()
        seconds.append(time.perf_counter() - started)
    return statistics.median(seconds), result


def _same(a, b) -> bool:
    """Bitwise equality of two results (arrays, tuples of arrays, dataclasses of arrays, None)."""
    if a is None or b is None:
        return a is None and b is None
    if isinstance(a, np.ndarray):
        return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()
    if isinstance(a, tuple):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if hasattr(a, "__dataclass_fields__"):
        return all(_same(getattr(a, f), getattr(b, f)) for f in a.__dataclass_fields__)
    return a == b


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", default=os.path.join(ROOT, "benchmarks", "results", "fixed_costs.json"))
    args = parser.parse_args(argv)

    from benchmarks.run import write_results
    from tools.visibake import loaded_extension

    _, module = loaded_extension()
    import bpy

    kernels = module("core.kernels")
    status = kernels.status()
    if status.backend != "numba":
        print(f"compiled kernels unavailable ({status.reason}): nothing to compare", file=sys.stderr)
        return 2
    rows = []

    def compare(name, reference_call, compiled_call, reference="numpy", checked=True):
        """Time the reference path (the numpy fallback, or what ``reference`` names) against the
        compiled one; ``checked`` False: results that cannot be compared (bitwise "n/a")."""
        reference_seconds, expected = timed(reference_call, args.repeats)
        compiled_seconds, got = timed(compiled_call, args.repeats)
        rows.append({"pass": name, "reference": reference, "reference_seconds": round(reference_seconds, 4),
                     "compiled_seconds": round(compiled_seconds, 4),
                     "speedup": round(reference_seconds / max(compiled_seconds, 1e-9), 1),
                     "bitwise": _same(expected, got) if checked else "n/a"})
        verdict = {True: "equal", False: "DIFFERENT", "n/a": "n/a"}[rows[-1]["bitwise"]]
        print(f"{name}: {reference} {reference_seconds:.3f} s, VisiBake's {compiled_seconds:.3f} s, "
              f"bitwise {verdict}", flush=True)

    def without_kernels(call):
        """``call`` as a process without the compiled kernels runs it (their numpy fallback)."""
        def uncompiled():
            compiled = kernels._module
            kernels._module = None
            try:
                return call()
            finally:
                kernels._module = compiled
        return uncompiled

    # The dense mesh's UV rasterisation.
    scenes = importlib.import_module("benchmarks.scenes")
    raster = module("core.sampling.raster")
    bpy.ops.wm.read_homefile(use_empty=True)
    terrain = scenes.dense_mesh()[0]
    mesh = terrain.data
    mesh.calc_loop_triangles()
    loops = np.empty(len(mesh.loop_triangles) * 3, np.int32)
    mesh.loop_triangles.foreach_get("loops", loops)
    uv = np.empty(len(mesh.loops) * 2, np.float32)
    mesh.uv_layers["UVMap"].data.foreach_get("uv", uv)
    corner_uv = uv.reshape(-1, 2)[loops].reshape(-1, 3, 2)
    for size in (64, 2048):
        compare(f"rasterize dense_mesh ({len(corner_uv)} triangles) at {size}^2",
                lambda size=size: raster._rasterize_numpy(corner_uv, size, size),
                lambda size=size: raster.rasterize(corner_uv, size, size))
    atlas = module("core.sampling.atlas")
    compare("UV layout check of dense_mesh at 64^2", without_kernels(lambda: atlas.uv_layout_stats(corner_uv, 64, 64)),
            lambda: atlas.uv_layout_stats(corner_uv, 64, 64))
    extract = module("operators.adapter.extract")

    def per_triangle_reads():
        count = len(mesh.loop_triangles)
        return (extract.read_values(mesh.vertices, "co", len(mesh.vertices), 3, np.float64),
                extract.read_values(mesh.loop_triangles, "vertices", count, 3, np.int32),
                extract.read_values(mesh.loop_triangles, "loops", count, 3, np.int64),
                extract.read_values(mesh.loop_triangles, "material_index", count, 1, np.int32))

    def attribute_reads():
        read = extract.read_triangles(mesh)
        return read.positions, read.triangles, read.loops, read.material_index
    compare("read of dense_mesh's positions and loop triangles (vertices, loops, materials)", per_triangle_reads,
            attribute_reads, "foreach_get of each property")
    read = extract.read_triangles(mesh)
    positions, triangles = read.positions, read.triangles
    face_frames = module("core.geometry")._face_frames
    compare("face normals and areas of dense_mesh", without_kernels(lambda: face_frames(positions, triangles)),
            lambda: face_frames(positions, triangles))
    rays = module("core.visibility.rays")
    import embreex.mesh_construction
    import embreex.rtcore_scene
    vertices32, indices32 = positions.astype(np.float32), triangles.astype(np.int32)

    def embree_copy(feed):
        # Building the scene too: embreex's TriangleMesh needs one, and its cost is the same both ways.
        scene = embreex.rtcore_scene.EmbreeScene()
        feed(embreex.mesh_construction.TriangleMesh, scene, vertices32, indices32)
        return None
    compare("embree's copy of dense_mesh", lambda: embree_copy(lambda make, *a: make(*a)),
            lambda: embree_copy(rays._triangle_mesh), "embreex TriangleMesh on numpy arrays", checked=False)
    shared = module("core.visibility.embree_shared")

    def attached_where_it_lies():
        scene, device = shared.new_scene()
        if shared.attach(scene, device, shared.padded_vertices(vertices32), indices32) != 0:
            raise RuntimeError("embree_shared could not attach dense_mesh here")
    compare("dense_mesh handed to embree without a copy (speed part 17)", lambda: embree_copy(rays._triangle_mesh),
            attached_where_it_lies, "embreex TriangleMesh on Python objects (part 14)", checked=False)

    # The demo's per-preparation passes and its lamps.
    bpy.ops.wm.read_homefile(use_empty=True)
    objects = module("operators.adapter.demo_scene").build_demo_scene(bpy.context.scene)
    props = bpy.context.scene.visibake
    props.passes = {"lighting"}
    settings = module("operators.adapter.settings").bake_settings(props)
    scene = module("operators.adapter.extraction").extract_scene(bpy.context, objects).scene
    p = module("core.pipeline.prepare").prepare(scene, settings, table_needed=True)
    contacts = module("core.transport.contacts")
    interleave = module("core.transport.interleave")
    reach = contacts.SHORT_HIT_TEXELS * contacts.texel_sizes(p.meshes, p.object_samples)
    slots = p.footprint[0].shape[1]
    compare("close_entries (short-hit reach)", lambda: contacts._close_entries_numpy(p, reach),
            lambda: contacts.close_entries(p, reach))
    compare("exposed_share", lambda: contacts._exposed_share_numpy(p.table, slots),
            lambda: contacts.exposed_share(p.table, slots))
    close = contacts.close_entries(p, reach)
    obj, uv_hits = close.obj, close.uv
    compare("texel owners of the short hits", lambda: contacts._texel_owners_numpy(p, obj, uv_hits),
            lambda: contacts._texel_owners(p, obj, uv_hits))
    compare("filter_pairs (with its occlusion rays)", lambda: interleave._filter_pairs_numpy(p),
            lambda: interleave.filter_pairs(p))

    footprint = module("core.sampling.footprint")
    largest = max((i for i, s in enumerate(p.object_samples) if s.footprint is not None),
                  key=lambda i: len(p.object_samples[i].position))
    mesh, own = p.meshes[largest], p.object_samples[largest]
    arguments = (own.pixel, own.triangle, own.width, own.height, np.asarray(mesh.uv_maps[mesh.bake_uv_map], np.float64),
                 mesh.positions[mesh.triangles].astype(np.float64), own.position, slots)

    compare(f"footprint points of {mesh.name} ({len(own.position)} samples x {slots})",
            without_kernels(lambda: footprint.footprint_offsets(*arguments)),
            lambda: footprint.footprint_offsets(*arguments))

    direct = module("core.transport.direct")
    lamps = module("core.lights.lamps")
    samples, shadowing = p.sample_set(), p.shadowing()
    one_pass = lamps.LampPoints.add_untraced
    for light in scene.lights:
        def looped(light=light):
            lamps.LampPoints.add_untraced = lambda *arguments: None
            try:
                return direct.lamp_irradiance(samples, shadowing, [light])
            finally:
                lamps.LampPoints.add_untraced = one_pass
        compare(f"direct light of {light.name} ({light.kind}, {len(samples.position)} samples)", looped,
                lambda light=light: direct.lamp_irradiance(samples, shadowing, [light]), "point-by-point loop")

    # The shadow rays of each lamp's first corner probe (as direct._penumbra_probes makes them):
    # every sample's, from its texel box's corner, lifted where its face is smooth.
    LightContribution = lamps.LightContribution
    for light in scene.lights:
        blockers = shadowing.blocker_scene(light)
        moved = samples.position + samples.footprint_corners[:, 0]
        to_light, distance = lamps.centre_probe(light, moved)
        aimed = np.nonzero(np.einsum("kd,kd->k", to_light, samples.normal) > 0.0)[0]
        probe = LightContribution(None, to_light, distance, moved)

        numpy_rays = without_kernels(lambda blockers=blockers, probe=probe, aimed=aimed:
                                     direct.shadow_rays(blockers, samples, probe, aimed))
        compare(f"shadow rays' set-up, {light.name}'s corner probe ({len(aimed)} rays)", numpy_rays,
                lambda blockers=blockers, probe=probe, aimed=aimed: direct.shadow_rays(blockers, samples, probe, aimed))

    write_results(args.out, {"settings": {"repeats": args.repeats, "demo_directions": settings.directions,
                                          "demo_samples": int(len(p.position))},
                             "kernels": status.describe(), "passes": rows})
    return 0 if all(row["bitwise"] is not False for row in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
