"""Both transport backends implement the contract, and a whole relight is the same on either.

The per-pass twins (test_gather_twin, test_direct_twin, test_dilate_twin,
test_passes_twin) check each pass alone; this runs ``relight_many`` end to end, so
the pipeline's use of the contract (which structures go where, the device in the
report) is checked too. Tolerance as the gather twin's: float32 sums on the GPU.
"""
import importlib
import importlib.util
import inspect
from pathlib import Path

import numpy as np
import pytest

CORE_SCENES = Path(__file__).resolve().parents[1] / "core" / "core_scenes.py"
CONTRACT_METHODS = ("lamp_irradiance", "gather", "accumulate_passes", "dilate")


def _builders(core):
    spec = importlib.util.spec_from_file_location("contract_core_scenes", CORE_SCENES)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    module.Mesh, module.Material = core.scene.Mesh, core.scene.Material
    return module


@pytest.fixture(scope="module")
def backends(visibake, gpu_shaders):
    cpu = importlib.import_module(f"{visibake.__name__}.core.transport.cpu").CPU_BACKEND
    gpu = importlib.import_module(f"{visibake.__name__}.gpu_shaders.backend").GPUBackend(256 << 20)
    return cpu, gpu


def test_both_backends_have_the_contract_s_methods_and_parameters(visibake, backends):
    contract = importlib.import_module(f"{visibake.__name__}.core.transport.contract").TransportBackend
    for backend in backends:
        assert backend.name in ("cpu", "gpu")
        for name in CONTRACT_METHODS:
            wanted = list(inspect.signature(getattr(contract, name)).parameters)[1:]  # without self
            assert list(inspect.signature(getattr(backend, name)).parameters) == wanted, (backend.name, name)


@pytest.mark.parametrize("shadows", ["exact", "fractions"])
def test_a_relight_is_the_same_on_either_backend(visibake, backends, shadows):
    core = visibake.core
    builders = _builders(core)
    glow = core.scene.Material(base_color=np.array([0.7, 0.6, 0.5]), emission=np.array([3.0, 3.0, 2.0]))
    meshes = [builders.box_interior(size=2.0, resolution=24),
              builders.quad_mesh("Glow", [(-0.3, -0.3, -0.9), (0.3, -0.3, -0.9), (0.3, 0.3, -0.9),
                                          (-0.3, 0.3, -0.9)], material=glow, resolution=8)]
    lights = [core.scene.Light("Lamp", "POINT", np.ones(3), 60.0, position=np.array([0.2, 0.1, 0.5])),
              core.scene.Light("Sun", "SUN", np.array([1.0, 0.9, 0.8]), 2.0,
                               direction=np.array([0.3, -0.2, -1.0]) / np.linalg.norm([0.3, -0.2, -1.0]))]
    settings = core.settings.BakeSettings(directions=48, bounces=2, shadows=shadows, passes=("lighting", "ao"),
                                          light_groups=True)
    prepared = core.pipeline.prepare.prepare(core.scene.Scene(meshes, lights), settings, table_needed=True)
    cpu, gpu = backends
    results = [core.pipeline.relight.relight(prepared, lights, core.scene.World(), backend=backend)
               for backend in (cpu, gpu)]
    for backend, result in zip((cpu, gpu), results):
        devices = {entry["device"] for entry in result.report["passes"]}
        assert devices == {backend.name}, devices
    for ours, twin in zip(results[1].objects, results[0].objects):
        assert ours.images.keys() == twin.images.keys() and "lighting_Lamp" in twin.images
        for name, image in twin.images.items():
            assert np.abs(image).max() > 0 or name == "ao", name
            np.testing.assert_allclose(ours.images[name], image, rtol=1e-4, atol=1e-5 * max(np.abs(image).max(), 1),
                                       err_msg=f"{ours.name} {name}")
