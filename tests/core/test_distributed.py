"""Scale-out (issue 20): the rules for joining a scheduler, and bakes whose table is traced and
read by row ranges on a real Dask scheduler and two worker processes on 127.0.0.1, started
and stopped here: bit-identical to the one-process bake, also after a worker is killed in
the middle of the run."""
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from core.distributed import engine
from core.distributed.package import write_package
from core.distributed.rows import row_ranges
from core.pipeline.prepare import prepare
from core.pipeline.relight import bake
from core.scene import Light, Scene
from core.settings import BakeSettings
from core_scenes import box_interior, quad_mesh

REPO_ROOT = Path(__file__).resolve().parents[2]
TABLE_ARRAYS = ("hit_object", "hit_uv_code", "hit_distance_code")


def test_loopback_tcp_is_joined_and_anything_else_needs_tls_or_insecure():
    assert engine.check_scheduler_address("tcp://127.0.0.1:8786") == "tcp://127.0.0.1:8786"
    assert engine.check_scheduler_address("tcp://localhost:8786")
    assert engine.check_scheduler_address("tcp://[::1]:8786")
    with pytest.raises(engine.ClusterRefused, match="not encrypted.*--insecure"):
        engine.check_scheduler_address("tcp://10.20.30.40:8786")
    assert engine.check_scheduler_address("tcp://10.20.30.40:8786", insecure=True)
    with pytest.raises(engine.ClusterRefused, match="needs the certificates"):
        engine.check_scheduler_address("tls://10.20.30.40:8786")
    tls = engine.TLSFiles("ca.pem", "cert.pem", "key.pem")
    assert engine.check_scheduler_address("tls://10.20.30.40:8786", tls)
    for wrong in ("10.20.30.40:8786", "http://127.0.0.1:8786", "tcp://127.0.0.1", "tcp://:8786"):
        with pytest.raises(engine.ClusterRefused, match="tcp://HOST:PORT"):
            engine.check_scheduler_address(wrong)
    with pytest.raises(engine.ClusterRefused, match="at least 1"):
        with engine.cluster_client(workers=0):
            pass


def test_row_ranges_cover_the_samples_and_depend_on_the_counts_alone():
    for samples, parts in ((10, 3), (7, 7), (1000, 4), (5, 8)):
        ranges = row_ranges(samples, parts)
        assert ranges == row_ranges(samples, parts)
        assert [i for r in ranges for i in r] == list(range(samples))


def _bake(tmp_path, resolution):
    """A closed box with a card inside, interleaved rotations and texel footprints, lit by a
    lamp: the packaged bake's bytes, its scene and settings, and its one-process bake."""
    card = quad_mesh("Card", [(-0.2, -0.2, -0.1), (0.2, -0.2, -0.1), (0.2, 0.2, 0.1), (-0.2, 0.2, 0.1)],
                     resolution=resolution // 2)
    scene = Scene([box_interior(resolution=resolution), card],
                  [Light("Lamp", "POINT", np.ones(3), 50.0, position=np.array([0.1, 0.2, 0.3]))])
    settings = BakeSettings(directions=128, bounces=2, interleave=2, footprint_samples=4, seed=3,
                            passes=("lighting", "indirect", "ao"))
    path = tmp_path / "bake.vbpkg"
    write_package(path, scene, settings)
    return path.read_bytes(), scene, settings, bake(scene, settings)


def _same_images(ours, theirs):
    for a, b in zip(ours.objects, theirs.objects, strict=True):
        assert list(a.images) == list(b.images)
        for name in a.images:
            assert np.array_equal(a.images[name], b.images[name]), (a.name, name)


def _same_table(table, reference):
    for name in TABLE_ARRAYS:
        assert np.array_equal(getattr(table, name), getattr(reference, name)), name
    assert table.rays_cast == reference.rays_cast
    assert np.array_equal(table.buried(), reference.buried())


class _Cluster:
    """``dask scheduler`` and ``dask worker`` processes on 127.0.0.1 (the repository on their
    path, this test session's compiled-kernel cache shared)."""

    def __init__(self, folder: Path, workers: int):
        self.scheduler_file = folder / "scheduler.json"
        environment = dict(os.environ, PYTHONPATH=str(REPO_ROOT), DASK_DISTRIBUTED__WORKER__DAEMON="False")
        self.scheduler = subprocess.Popen(
            [sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1", "--port", "0",
             "--no-dashboard", "--scheduler-file", str(self.scheduler_file)],
            env=environment, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        deadline = time.monotonic() + 60
        while not self.scheduler_file.exists():
            if time.monotonic() > deadline or self.scheduler.poll() is not None:
                self.close()
                raise RuntimeError("the dask scheduler did not start")
            time.sleep(0.2)
        self.workers = [subprocess.Popen(
            [sys.executable, "-m", "distributed.cli.dask_worker", "--scheduler-file", str(self.scheduler_file),
             "--nworkers", "1", "--nthreads", "1", "--no-dashboard", "--name", f"w{number}",
             "--local-directory", str(folder / f"w{number}")],
            env=environment, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL) for number in range(workers)]

    def client(self, workers: int):
        from distributed import Client

        client = Client(scheduler_file=str(self.scheduler_file), timeout=60)
        client.wait_for_workers(workers, timeout=120)
        return client

    def close(self):
        for process in [*getattr(self, "workers", []), self.scheduler]:
            if process.poll() is None:
                process.terminate()
        for process in [*getattr(self, "workers", []), self.scheduler]:
            try:
                process.wait(timeout=30)
            except subprocess.TimeoutExpired:
                process.kill()


@pytest.fixture
def cluster(tmp_path):
    running = _Cluster(tmp_path, workers=2)
    yield running
    running.close()


def test_two_workers_bake_by_rows_bit_identical(cluster, tmp_path):
    package, scene, settings, whole = _bake(tmp_path, 48)
    client = cluster.client(2)
    try:
        rows = engine.ClusterRows(client, package, parts=5)
        fractions = []
        split = bake(scene, settings, lambda stage, fraction: fractions.append(fraction) if stage == "visibility"
                     else None, split=rows)
        _same_images(split, whole)
        assert len(set(rows.placement.values())) == 2  # both workers hold rows
        assert 1.0 in fractions
        # The rows' tables, brought back for this check only, join to the one-process table.
        p = prepare(scene, settings, table_needed=True)
        joined = prepare(scene, settings, table_needed=True, split=rows).table.whole()
        _same_table(joined, p.table)
    finally:
        client.close()


def test_a_worker_killed_mid_run_changes_nothing(cluster, tmp_path):
    package, scene, settings, whole = _bake(tmp_path, 96)
    client = cluster.client(2)
    try:
        victim = cluster.workers[0]
        killed = []

        def kill_once(stage, fraction):
            # After the first range is traced, the first worker is killed while the rest run or wait.
            if stage == "visibility" and fraction > 0 and not killed:
                victim.send_signal(signal.SIGKILL)
                killed.append(fraction)

        rows = engine.ClusterRows(client, package, parts=12)
        split = bake(scene, settings, kill_once, split=rows)
        victim.wait(timeout=30)
        assert killed and victim.returncode == -signal.SIGKILL
        _same_images(split, whole)
        assert len(set(rows.placement.values())) == 1  # the survivor traced the dead worker's rows again
    finally:
        client.close()


def test_a_brdf_run_in_parts_on_two_workers_survives_a_killed_worker(cluster):
    from benchmarks import brdf_tiles
    from core.appearance import gonio
    from core.appearance.tile import Tile
    from core.distributed.package import PackageRefused
    from core.version import visibake_version

    tile = Tile.of(*brdf_tiles.v_groove_tile(0.5), albedo=0.7)
    lights, views = gonio.sphere_directions(200), gonio.hemisphere_directions(8)
    settings = gonio.GonioSettings(directions=64, bounces=2, resolution=16, view_rays=64, seed=1)
    whole = gonio.simulate_brdf(tile, lights, views, settings)
    client = cluster.client(2)
    try:
        victim, killed = cluster.workers[0], []

        def kill_once(fraction):
            if not killed:
                victim.send_signal(signal.SIGKILL)
                killed.append(fraction)

        arguments = [(visibake_version(), tile, lights, views, settings, index, 4) for index in range(4)]
        joined = gonio.join_brdf_parts(engine.run_parts(client, "brdf_part", arguments, kill_once))
        victim.wait(timeout=30)
        assert killed and victim.returncode == -signal.SIGKILL
        for name in ("light", "values", "transparency"):
            assert np.array_equal(getattr(joined, name), getattr(whole, name)), name
        # A driver of another VisiBake version is refused by the worker, with both versions named.
        with pytest.raises(PackageRefused, match="this worker runs VisiBake .*, the driver 0.0.0-other"):
            engine.run_parts(client, "brdf_part", [("0.0.0-other", tile, lights[:2], views, settings, 0, 1)])
    finally:
        client.close()


def test_a_local_cluster_starts_on_loopback_and_leaves_no_process_behind():
    import psutil

    from core.distributed.package import PackageRefused

    before = {child.pid for child in psutil.Process().children(recursive=True)}
    with engine.cluster_client(workers=2) as client:
        addresses = engine.worker_addresses(client)
        assert len(addresses) == 2 and all(a.startswith("tcp://127.0.0.1:") for a in addresses)
        # The client's periodic refresh caches an identity without workers; the workers are
        # still found (CI of stop 35 read that cache and found none).
        client.sync(client._update_scheduler_info, n_workers=0)
        assert not client._scheduler_identity["workers"]
        assert engine.worker_addresses(client) == addresses
        started = [child for child in psutil.Process().children(recursive=True) if child.pid not in before]
        assert len(started) >= 3  # the scheduler and two workers (and what their nannies started)
        # The workers import VisiBake's core through the preload, and refuse another version's tasks.
        with pytest.raises(PackageRefused, match="the driver other"):
            engine.run_parts(client, "brdf_part", [("other", None, None, None, None, 0, 1)])
        # Nor do they run with the nanny's malloc trimming, which slowed a range's work 1.3-2.5x.
        environments = client.run(lambda: dict(os.environ))
        assert len(environments) == 2
        assert not [e for e in environments.values() if "MALLOC_TRIM_THRESHOLD_" in e]
        assert all(e.get("OMP_NUM_THREADS") == "1" for e in environments.values())  # the rest of its defaults stay
    # The scheduler and the nannies were waited for; what a nanny started ends with it, soon after.
    _, alive = psutil.wait_procs(started, timeout=30)
    assert not [p for p in alive if p.status() != psutil.STATUS_ZOMBIE]
