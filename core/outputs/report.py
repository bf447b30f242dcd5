"""The bake report: what one bake did, as typed records and their JSON form.

:func:`lighting_report` builds the core's part of a report from a prepared scene and
one lighting; the Blender job fills in the rest (files, total time, device, setups)
through the same fields. ``Report.to_dict()`` is the JSON form: the ``report.json`` a
bake writes, ``BakeResult.report``, and what the panel keeps on the scene.
``Report.from_dict`` reads it back: strictly where the job extends a report (a field
of another schema is an error), leniently for the texts (a report kept in a .blend by
another version shows what this one knows; missing fields take their defaults).

Its texts (the operator's line, the terminal summary, the panel's rows) come from the
one formatter in :mod:`core.outputs.summary`.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields, replace
from typing import TYPE_CHECKING

import numpy as np

from .. import kernels
from ..distributed.split import SplitTable
from ..transport.contract import Shadowing
from ..transport.estimate import lighting_error
from ..visibility.cache import CacheStatus
from .diagnostics import check_vertex_objects

if TYPE_CHECKING:
    from ..pipeline.prepare import Prepared


def _kwargs(cls, data: dict, strict: bool) -> dict:
    """``data`` as keyword arguments of ``cls``. A key ``cls`` has no field for is an error
    when ``strict`` (a report of another schema is refused rather than half read), else
    left out (texts of a report saved by another version show what this one knows)."""
    names = {f.name for f in fields(cls)}
    unknown = set(data) - names
    if unknown and strict:
        raise ValueError(f"{cls.__name__}: unknown report fields {sorted(unknown)}")
    return {k: v for k, v in data.items() if k in names}


def _shallow(record) -> dict:
    """A record's fields as a dict, its containers shared (see :class:`Report`)."""
    return {f.name: getattr(record, f.name) for f in fields(record)}


def _without_none(pairs: dict) -> dict:
    """Optional fields appear in the JSON only once something set them."""
    return {k: v for k, v in pairs.items() if v is not None}


@dataclass
class ObjectReport:
    """One object of the bake: its layout and sample counts."""

    name: str
    output: bool  # False: it only occludes and reflects
    uv_map: str
    resolution: list  # [width, height]; vertex mode: [samples, 1]
    texels: int  # samples placed on it
    triangles: int
    # Only when the table saw backface hits: samples most of whose rays hit the back of a
    # face (inside other geometry).
    buried_texels: int | None = None
    # Vertex mode, with lamps: triangles whose direct light varies inside them.
    under_tessellated_triangles: int | None = None
    under_tessellated_area_share: float | None = None
    # Atlas mode with seam stitching on: seam edges between smooth faces stitched, and the RMS
    # disagreement of the two sides' bilinear lookups along them, relative to the object's
    # mean light, before and after (core.outputs.seams).
    seam_edges: int | None = None
    seam_disagreement: list | None = None  # [before, after]
    # The bake's estimate of its own error on the lighting pass (core.transport.estimate):
    # {"total", "direct", "indirect"}, relative RMS per texel; output objects only.
    estimated_error: dict | None = None
    # Set by the Blender job from its layout plan.
    mode: str | None = None  # 'atlas' | 'vertex'
    layout_reason: str | None = None
    uv_map_created: bool | None = None

    def to_dict(self) -> dict:
        always = {"name": self.name, "output": self.output, "uv_map": self.uv_map, "resolution": self.resolution,
                  "texels": self.texels, "triangles": self.triangles}
        return {**always, **_without_none({
            "buried_texels": self.buried_texels, "under_tessellated_triangles": self.under_tessellated_triangles,
            "under_tessellated_area_share": self.under_tessellated_area_share,
            "seam_edges": self.seam_edges, "seam_disagreement": self.seam_disagreement,
            "estimated_error": self.estimated_error, "mode": self.mode,
            "layout_reason": self.layout_reason, "uv_map_created": self.uv_map_created})}

    @classmethod
    def from_dict(cls, data: dict, strict: bool = True) -> "ObjectReport":
        defaults = {"name": "", "output": True, "uv_map": "", "resolution": [0, 0], "texels": 0, "triangles": 0}
        return cls(**{**defaults, **_kwargs(cls, data, strict)})


@dataclass
class Rays:
    """Rays of the bake: visibility rays (cast now, or in the cached table) and shadow rays."""

    visibility_cast: int = 0  # traced by this bake (0 on a cache hit)
    visibility_in_table: int = 0
    visibility_skipped_below_horizon: int = 0
    backface_hits: int = 0
    shadow_rays: int = 0  # exact shadows
    emitter_rays: int = 0  # sampled emitters

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict, strict: bool = True) -> "Rays":
        return cls(**_kwargs(cls, data, strict))


@dataclass
class PassReport:
    """One transport pass and where it ran (core.pipeline.progress.Stages.record_pass)."""

    name: str
    device: str
    seconds: float

    def to_dict(self) -> dict:
        return {"pass": self.name, "device": self.device, "seconds": self.seconds}

    @classmethod
    def from_dict(cls, data: dict, strict: bool = True) -> "PassReport":
        data = dict(data)
        return cls(**_kwargs(cls, {"name": data.pop("pass", ""), **data}, strict))


@dataclass
class DeviceReport:
    """The device the transport ran on (operators.adapter.device.choose)."""

    requested: str = ""
    used: str = ""
    reason: str = ""
    # The GPU context, where one was made (gpu_shaders.runtime.DeviceInfo).
    backend: str | None = None
    renderer: str | None = None
    vendor: str | None = None
    version: str | None = None
    software: bool | None = None
    gpu_memory_budget_mib: int | None = None

    def to_dict(self) -> dict:
        return {"requested": self.requested, "used": self.used, "reason": self.reason, **_without_none({
            "backend": self.backend, "renderer": self.renderer, "vendor": self.vendor, "version": self.version,
            "software": self.software, "gpu_memory_budget_mib": self.gpu_memory_budget_mib})}

    @classmethod
    def from_dict(cls, data: dict, strict: bool = True) -> "DeviceReport":
        return cls(**_kwargs(cls, data, strict))


@dataclass
class SetupReport:
    """One lighting setup of a bake with setups (files only)."""

    name: str
    lights: list  # names of its lamps
    stage_seconds: dict
    gathers: int
    shadow_rays: int
    lighting_reused: list

    def to_dict(self) -> dict:
        return _shallow(self)

    @classmethod
    def from_dict(cls, data: dict, strict: bool = True) -> "SetupReport":
        return cls(**_kwargs(cls, data, strict))


@dataclass
class RefinedReport:
    """A vertex-mode object baked again as a refined copy (operators.adapter.refine)."""

    object: str
    copy: str
    coarse_triangles: int
    vertices: list  # [original, copy]

    def to_dict(self) -> dict:
        return _shallow(self)

    @classmethod
    def from_dict(cls, data: dict, strict: bool = True) -> "RefinedReport":
        return cls(**_kwargs(cls, data, strict))


_OFF = {"state": "off", "lighting_reused": []}


@dataclass
class Report:
    """Everything one bake reports, in the order of its JSON form.

    Containers (lists, dicts) are shared with the dict ``to_dict`` returns, not copied,
    so code that extends the dict (the command line appends the files it writes) and
    the record agree.
    """

    settings: dict = field(default_factory=dict)  # dataclasses.asdict(core.settings.BakeSettings)
    objects: list[ObjectReport] = field(default_factory=list)
    stage_seconds: dict = field(default_factory=dict)  # stage name -> seconds, in the order they ran
    lightings_transported_together: int = 1
    rays: Rays = field(default_factory=Rays)
    light_groups: list = field(default_factory=list)
    emitters_sampled: list = field(default_factory=list)
    gathers: int = 0
    table_bytes: int = 0
    # The cache's record of this bake, lighting_reused set to the light groups read back;
    # None: no cache status at all (reported as off).
    cache: CacheStatus | None = None
    skipped: list = field(default_factory=list)  # work not done, and why
    warnings: list = field(default_factory=list)
    passes: list[PassReport] = field(default_factory=list)
    # How the CPU lookups ran (core.kernels.KernelStatus.as_dict); empty in reports from before.
    kernels: dict = field(default_factory=dict)
    # A table held by sample rows (core.distributed.split.SplitTable.describe, plus the job's
    # cluster: workers, scheduler); None for a bake in one process, and left out of the JSON.
    split: dict | None = None
    # Set by the Blender job (operators.adapter.job); None until then, and left out of the JSON.
    total_seconds: float | None = None
    peak_memory_bytes: int | None = None
    files: list | None = None
    blender_version: str | None = None
    lights: list | None = None
    relight_only: bool | None = None
    device: DeviceReport | None = None
    setups: list[SetupReport] | None = None
    refined: list[RefinedReport] | None = None
    # Outputs whose file or image is not named after their object, pass or setup (unsafe or
    # colliding names, core.outputs.names): [{"name", "kind" (object|pass|setup|image), "path"}].
    renamed_outputs: list | None = None
    # The bake's estimate of its own error on the lighting pass over the output objects
    # (core.transport.estimate.lighting_error: total, direct, indirect, unestimated_share);
    # None where it has none (light read back from a cache, or no lighting pass).
    estimated_error: dict | None = None
    # Set by the Blender job at a Target Error (core.pipeline.target.DirectionChoice.as_dict, plus
    # estimated_error and met); None otherwise, and left out of the JSON.
    target: dict | None = None

    def to_dict(self) -> dict:
        """The JSON form (the keys and nesting of ``report.json``)."""
        if self.cache is None:
            cache = dict(_OFF, lighting_reused=[])
        else:
            cache = asdict(self.cache)
        return {
            "settings": self.settings,
            "objects": [o.to_dict() for o in self.objects],
            "stage_seconds": self.stage_seconds,
            "lightings_transported_together": self.lightings_transported_together,
            "rays": self.rays.to_dict(),
            "light_groups": self.light_groups,
            "emitters_sampled": self.emitters_sampled,
            "gathers": self.gathers,
            "table_bytes": self.table_bytes,
            "cache": cache,
            "skipped": self.skipped,
            "warnings": self.warnings,
            "estimated_error": self.estimated_error,
            "kernels": self.kernels,
            "passes": [p.to_dict() for p in self.passes],
            **_without_none({
                "total_seconds": self.total_seconds, "peak_memory_bytes": self.peak_memory_bytes,
                "files": self.files, "blender_version": self.blender_version, "lights": self.lights,
                "relight_only": self.relight_only, "split": self.split,
                "device": self.device.to_dict() if self.device is not None else None,
                "setups": [s.to_dict() for s in self.setups] if self.setups is not None else None,
                "refined": [r.to_dict() for r in self.refined] if self.refined is not None else None,
                "renamed_outputs": self.renamed_outputs, "target": self.target}),
        }

    @classmethod
    def from_dict(cls, data: dict, strict: bool = True) -> "Report":
        """The record of a report's JSON form; missing fields take their defaults.

        ``strict``: a field (at any level) this version does not know raises ValueError;
        else it is left out.
        """
        values = _kwargs(cls, data, strict)
        values["objects"] = [ObjectReport.from_dict(o, strict) for o in values.get("objects", [])]
        values["rays"] = Rays.from_dict(values.get("rays", {}), strict)
        cache = values.get("cache")
        values["cache"] = None if cache is None or cache == _OFF else CacheStatus(**_kwargs(CacheStatus, cache, strict))
        values["passes"] = [PassReport.from_dict(p, strict) for p in values.get("passes", [])]
        # An empty device (a report from before the device was reported) is none.
        values["device"] = DeviceReport.from_dict(values["device"], strict) if values.get("device") else None
        if values.get("setups") is not None:
            values["setups"] = [SetupReport.from_dict(s, strict) for s in values["setups"]]
        if values.get("refined") is not None:
            values["refined"] = [RefinedReport.from_dict(r, strict) for r in values["refined"]]
        return cls(**values)

    @property
    def output_objects(self) -> list[ObjectReport]:
        return [o for o in self.objects if o.output]

    @property
    def cache_state(self) -> str:
        return self.cache.state if self.cache is not None else "off"


def _rounded(value: float | None) -> float | None:
    """A relative error as the report keeps it: four significant digits."""
    return None if value is None else float(f"{value:.4g}")


def lighting_report(p: "Prepared", plan: dict, parts: dict, times: dict, passes: list, gathers: int,
                    shared_skips: list, lightings: int) -> Report:
    """The core's report of one lighting of ``relight_many`` (times, passes and gathers are
    those of the whole call).

    Parameters
    ----------
    plan : the lighting's plan in ``relight_many``: 'skipped', 'warnings' (extended here),
        'groups' and 'reused' (light groups read back from the cache)
    parts : light group name -> core.transport.groups.Transported
    passes : [{'pass', 'device', 'seconds'}] of core.pipeline.progress.Stages
    """
    table = p.table
    skipped, warnings = plan["skipped"] + shared_skips, plan["warnings"]
    # A cached table found damaged when it was read (after the plan was made).
    warnings += [w for w in p.warnings if w not in warnings]
    if plan["reused"]:
        names = "all lights" if plan["reused"] == ["all"] else ", ".join(repr(n) for n in plan["reused"])
        skipped.append(f"transport of {names}: lighting, materials and settings unchanged since a cached bake")
    counts = np.diff(p.sample_offset)
    empty = sum(s.width * s.height for s in p.object_samples) - int(counts.sum())
    skipped.append(f"{empty} atlas texels outside every UV island: not sampled, filled by dilation only")
    if table is not None:
        skipped.append(f"{table.rays_below_horizon} directions below a texel's horizon: not traced")
    occluders = [m.name for m in p.meshes if not m.output]
    if occluders:
        skipped.append(f"outputs of {len(occluders)} objects that only occlude and reflect: {', '.join(occluders)}")
    cache = replace(p.cache_status, lighting_reused=list(plan["reused"])) if p.cache_status is not None else None
    report = Report(
        settings=asdict(p.settings),
        objects=[ObjectReport(name=m.name, output=m.output, uv_map=m.bake_uv_map, resolution=list(m.resolution),
                              texels=int(counts[i]), triangles=int(len(m.triangles)))
                 for i, m in enumerate(p.meshes)],
        stage_seconds={k: round(v, 4) for k, v in {**p.stage_seconds, **times}.items()},
        lightings_transported_together=lightings,
        rays=Rays(
            visibility_cast=int(p.visibility_rays),
            visibility_in_table=int(table.rays_cast) if table else 0,
            visibility_skipped_below_horizon=int(table.rays_below_horizon) if table else 0,
            backface_hits=int(table.backface_hits) if table else 0,
            shadow_rays=int(sum(t.shadow_rays for t in parts.values())),
            emitter_rays=int(sum(t.emitter_rays for t in parts.values())),
        ),
        light_groups=[g.name for g in plan["groups"]] if p.settings.light_groups else [],
        emitters_sampled=sorted({n for t in parts.values() for n in t.emitters_sampled}),
        gathers=int(gathers),
        table_bytes=int(table.nbytes) if table else 0,
        cache=cache,
        skipped=skipped,
        warnings=warnings,
        passes=[PassReport.from_dict(entry) for entry in passes],
        kernels=kernels.status().as_dict(),
        split=table.describe() if isinstance(table, SplitTable) else None,
    )
    outputs = np.array([i for i, m in enumerate(p.meshes) if m.output], np.int64)
    estimate = lighting_error(p.albedo, parts, p.sample_offset, outputs) if parts else None
    if estimate is not None:
        for index, entry in estimate.pop("objects").items():
            report.objects[index].estimated_error = {k: _rounded(v) for k, v in entry.items()}
        report.estimated_error = {k: _rounded(v) for k, v in estimate.items()}
    if table is not None and table.backface_hits:
        buried = table.buried()
        for entry, a, b in zip(report.objects, p.sample_offset[:-1], p.sample_offset[1:]):
            entry.buried_texels = int(np.count_nonzero(buried[a:b]))
        visible = ~buried
        share = table.backface_per_sample[visible].sum() / max(int(table.traced_per_sample[visible].sum()), 1)
        if share > 0.01:
            warnings.append(f"{share:.1%} of the rays from visible texels hit the back of a face; backs reflect "
                            "no light (single-sided geometry or flipped normals)")
    return report


def report_tessellation(p: "Prepared", lights, objects: list, report: Report) -> None:
    """Per vertex-mode object: triangles whose light varies inside them (a warning if any).

    Also hands each such object of ``objects`` (core.pipeline.relight.ObjectResult) its
    flagged triangles, which the Blender job refines.
    """
    by_name = {o.name: o for o in objects}
    shadowing = Shadowing.exact(p.ray_scene, p.settings.area_light_samples)
    checks = check_vertex_objects(p.meshes, p.object_samples, p.sample_offset, p.position, p.normal, shadowing,
                                  lights)
    for index, check in checks.items():
        entry = report.objects[index]
        if entry.name in by_name:
            by_name[entry.name].coarse_triangles = check.flagged_triangles
        entry.under_tessellated_triangles = check.flagged
        entry.under_tessellated_area_share = round(check.area_share, 4)
        if check.flagged:
            report.warnings.append(
                f"object {entry.name!r}: {check.flagged} of {check.triangles} triangles "
                f"({check.area_share:.0%} of its area) have direct light varying inside them by up to "
                f"{check.worst:.0%}, which its vertices cannot show; subdivide it or bake it as an atlas")


def report_seams(report: Report, enabled: bool, seams: dict, stitched: dict) -> None:
    """Seam stitching's part of ``report``: per object its stitched seam edges and the
    disagreement along them before and after, and in ``skipped`` what was not stitched.

    seams : mesh index -> core.outputs.seams.Seams or None (no seam between smooth faces)
    stitched : mesh index -> (edges, before, after)
    """
    if not enabled:
        report.skipped.append("seam stitching: off")
        return
    for index, (edges, before, after) in stitched.items():
        entry = report.objects[index]
        entry.seam_edges = int(edges)
        entry.seam_disagreement = [round(float(before), 5), round(float(after), 5)]
    without = [report.objects[i].name for i, found in seams.items() if found is None]
    if without:
        report.skipped.append(f"seam stitching of {len(without)} objects without UV seams between smooth faces: "
                              + ", ".join(without))
