"""The one formatter of a bake report: the operator's one-line report
(:func:`summary_line`), the terminal summary (:func:`summary_lines`) and the panel's
Last Bake rows (:func:`panel_lines`), built from the same phrases so that the three say
each fact the same way."""
from __future__ import annotations

import os
from dataclasses import fields

from ..kernels import KernelStatus
from ..visibility.cache import CacheStatus
from .report import DeviceReport, Rays, Report

_KERNEL_FIELDS = {f.name for f in fields(KernelStatus)}


def _as_report(report: Report | dict) -> Report:
    # Lenient: the panel shows reports kept in .blend files saved by other versions.
    return report if isinstance(report, Report) else Report.from_dict(report, strict=False)


def _verb(report: Report) -> str:
    return "relit" if report.relight_only else "baked"


def _visibility_phrase(report: Report) -> str:
    if report.cache_state == "unused" and report.rays.visibility_cast:
        # Traced and not cached: a table held by row ranges (the cache's state says why).
        return f"{report.rays.visibility_cast} visibility rays"
    return {"hit": "visibility from the cache", "updated": "visibility updated for changed objects",
            "unused": "no visibility needed"}.get(report.cache_state, f"{report.rays.visibility_cast} visibility rays")


def _rays_phrase(rays: Rays) -> str:
    return (f"rays: {rays.visibility_cast} traced, {rays.visibility_skipped_below_horizon} skipped "
            f"below the horizon, {rays.shadow_rays} shadow rays")


def _device_phrase(device: DeviceReport) -> str:
    return (f"device: {device.used} ({device.reason})"
            + (f"; {device.backend}, {device.renderer}" if device.renderer else ""))


def _kernels_phrase(record: dict) -> str:
    """How the CPU lookups ran, from a report's ``kernels`` record (core.kernels.KernelStatus)."""
    return "CPU lookups: " + KernelStatus(**{k: v for k, v in record.items() if k in _KERNEL_FIELDS}).describe()


def _cache_phrase(cache: CacheStatus) -> str:
    return f"cache: {cache.state}" + (f" ({cache.message})" if cache.message else "")


def _estimate_phrase(estimate: dict) -> str:
    """The bake's estimate of its own error (core.transport.estimate), e.g. "estimated error 2.1%
    per texel (lamps 0.4%, gathered 2.0%)"."""
    def percent(value):
        return "-" if value is None else f"{100 * value:.1f}%"

    phrase = (f"estimated error {percent(estimate.get('total'))} per texel (lamps "
              f"{percent(estimate.get('lamps'))}, gathered {percent(estimate.get('gathered'))})")
    unestimated = estimate.get("unestimated_share")
    if unestimated:
        phrase += f", {100 * unestimated:.0f}% of texels without an estimate"
    return phrase


def _target_phrase(target: dict) -> str:
    """A Target Error bake's choice: "target error 3.0%: 256 directions (why); estimated 2.4%"."""
    estimated = target.get("estimated_error")
    verdict = "" if estimated is None else (f"; estimated {100 * estimated:.1f}%, "
                                            + ("within the target" if target.get("met") else "above the target"))
    return (f"target error {100 * target['target_error']:.1f}%: {target['directions']} directions "
            f"({target['reason']}){verdict}")


def _skipped_phrase(item: str) -> str:
    return f"skipped: {item}"


def summary_line(report: Report | dict) -> str:
    """The one-line report of the Bake and Relight operators."""
    report = _as_report(report)
    objects = report.output_objects
    texels = sum(o.texels for o in objects)
    return (f"VisiBake: {_verb(report)} {len(objects)} object(s), {texels} texels, {_visibility_phrase(report)}, "
            f"in {report.total_seconds or 0:.1f} s")


def summary_lines(report: Report | dict) -> list[str]:
    """The command line's summary, one line a fact (indented under a title)."""
    report = _as_report(report)
    lines = ["VisiBake relight finished" if report.relight_only else "VisiBake bake finished"]
    settings = report.settings
    lines.append(f"  settings: {settings['directions']} directions, {settings['bounces']} bounces, "
                 f"shadows {settings['shadows']}, passes {','.join(settings['passes'])}")
    for entry in report.objects:
        role = "baked" if entry.output else "occluder"
        if entry.mode == "vertex":
            lines.append(f"  {entry.name:<16} {role:<8} vertex   {entry.texels:>8} samples ({entry.layout_reason})")
        else:
            lines.append(f"  {entry.name:<16} {role:<8} {entry.resolution[0]}x{entry.resolution[1]} "
                         f"{entry.texels:>8} texels  UV map {entry.uv_map}")
    lines.append("  " + _rays_phrase(report.rays))
    if report.target is not None:
        lines.append("  " + _target_phrase(report.target))
    if report.estimated_error is not None:
        lines.append("  " + _estimate_phrase(report.estimated_error) + "; per object: " + ", ".join(
            f"{o.name} {100 * o.estimated_error['total']:.1f}%" for o in report.output_objects
            if o.estimated_error and o.estimated_error.get("total") is not None))
    if report.device is not None:
        lines.append("  " + _device_phrase(report.device))
    if report.split is not None and "ranges" in report.split:
        cluster = report.split.get("cluster") or {}
        where = (f"{cluster['workers']} local workers" if cluster.get("workers") else cluster.get("scheduler")
                 or cluster.get("farm") or report.split["executor"])
        lines.append(f"  split: the table in {report.split['ranges']} ranges of texels on {where}, "
                     f"{report.split['table_bytes_held_by_ranges'] / 2**20:.0f} MiB held there")
    if report.kernels:
        lines.append("  " + _kernels_phrase(report.kernels))
    for entry in report.passes:
        lines.append(f"  pass: {entry.name} on {entry.device}: {entry.seconds:.3f} s")
    cache = report.cache
    if report.cache_state != "off":
        lines.append("  " + _cache_phrase(cache)
                     + (f", {cache.bytes_on_disk / 2**20:.1f} MiB at {cache.path}" if cache.path else ""))
        if cache.evicted:
            freed = sum(entry["bytes"] for entry in cache.evicted) / 2**20
            lines.append(f"  cache limit: removed {len(cache.evicted)} least recently used cached tables "
                         f"({freed:.1f} MiB) to make room")
    for setup in report.setups or []:
        lines.append(f"  setup {setup.name}: {len(setup.lights)} lights, {setup.gathers} gathers"
                     + (f", reused {', '.join(setup.lighting_reused)}" if setup.lighting_reused else ""))
    lines.append("  seconds: " + ", ".join(f"{k} {v:.2f}" for k, v in report.stage_seconds.items())
                 + f"; total {report.total_seconds or 0:.2f}")
    lines.append(f"  peak memory: {(report.peak_memory_bytes or 0) / 2**20:.0f} MiB")
    for item in report.skipped:
        lines.append("  " + _skipped_phrase(item))
    for item in report.warnings:
        lines.append(f"  warning: {item}")
    # Distinct paths: a file written twice is one file on disk, and the count says what is there.
    written = len({os.path.realpath(path) for path in report.files or []})
    renamed = len(report.renamed_outputs or [])
    lines.append(f"  files: {written} written" + (f", {renamed} output name(s) changed" if renamed else ""))
    return lines


def panel_lines(report: Report | dict) -> list[tuple[str, str]]:
    """(text, icon) lines of the panel's Last Bake: stage times, rays, cache, device, skips, warnings."""
    report = _as_report(report)
    lines = [(f"{report.total_seconds or 0:.1f} s in total", "TIME")]
    for stage, seconds in report.stage_seconds.items():
        lines.append((f"{stage}: {seconds:.2f} s", "BLANK1"))
    lines.append((_rays_phrase(report.rays), "LIGHT_SUN"))
    if report.target is not None:
        lines.append((_target_phrase(report.target), "INFO"))
    if report.estimated_error is not None:
        lines.append((_estimate_phrase(report.estimated_error), "INFO"))
    if report.cache_state != "off":
        lines.append((_cache_phrase(report.cache), "FILE_CACHE"))
    if report.device is not None:
        lines.append((_device_phrase(report.device), "MEMORY"))
    if report.kernels:
        lines.append((_kernels_phrase(report.kernels), "MEMORY"))
    lines += [(_skipped_phrase(item), "FORWARD") for item in report.skipped]
    lines += [(item, "ERROR") for item in report.warnings]
    return lines
