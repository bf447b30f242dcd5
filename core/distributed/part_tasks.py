"""Runs split into independent parts (BRDF samples by light batches), as a cluster's worker
runs one part: each returns its share, and the driver joins the shares in part order.

A task is named by its function's name here; its first argument is the driver's VisiBake
version, and a worker of another version refuses the task (as a scene package of another
version is refused: their results could differ).
"""
from __future__ import annotations

from ..kernels import blas_on_one_thread
from ..version import visibake_version
from .package import PackageRefused


def check_version(expected: str) -> None:
    """PackageRefused unless this process runs VisiBake ``expected``."""
    if expected != visibake_version():
        raise PackageRefused(f"this worker runs VisiBake {visibake_version()}, the driver {expected}: start the "
                             "workers with the driver's VisiBake")


def brdf_part(version: str, tile, lights, views, settings, index: int, count: int):
    """Part ``index`` of ``count`` of core.appearance.gonio.simulate_brdf (its BRDFSamples)."""
    from ..appearance.gonio import simulate_brdf

    check_version(version)
    return simulate_brdf(tile, lights, views, settings, part=(index, count))


def btf_part(version: str, tile, lights, views, image_size, settings, per_pixel: int, folder: str,
             image_format: str, index: int, count: int) -> dict:
    """Part ``index`` of ``count`` of core.appearance.gonio.simulate_btf, its images written by
    their UTIA names into ``folder`` (the run's, which its core.appearance.btf.BTFWriter
    claimed on the driver: shared storage where the workers are other machines). Returns
    {"stats": the part's stats, "written": the relative paths it wrote}."""
    from ..appearance.btf import BTFImages
    from ..appearance.gonio import simulate_btf

    check_version(version)
    images = BTFImages(folder, image_format, image_size[0], image_size[1])
    stats = simulate_btf(tile, lights, views, image_size, images.write, settings, per_pixel, part=(index, count))
    return {"stats": stats, "written": images.written}


def lightfield_part(version: str, drawn, size, supersampling: int, filter_width: float, views: list, clip,
                    threads: int = 0) -> list:
    """Views of a light field ray cast on the CPU (core.lightfield.raycast.RaycastRenderer):
    views : [(index, view_matrix (4, 4), projection_matrix (4, 4), want_depth)]; returns
    [(index, radiance (height, width, 3) float32, depth or None)], each the same bits as the
    same view rendered in one process."""
    from ..lightfield.raycast import RaycastRenderer

    check_version(version)
    rendered = []
    with RaycastRenderer(drawn, size[0], size[1], supersampling, filter_width, threads) as renderer:
        for index, view_matrix, projection_matrix, want_depth in views:
            radiance, depth = renderer.render(view_matrix, projection_matrix, *clip, want_depth=want_depth)
            rendered.append((index, radiance, depth))
    return rendered


def run_part(task: str, *arguments):
    """The part task named ``task`` (a function of this module) on ``arguments``."""
    with blas_on_one_thread():
        return globals()[task](*arguments)
