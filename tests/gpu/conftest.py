"""Fixtures for the GPU passes: the installed extension, and its gpu_shaders with a context.

Every test here compares a GPU pass with its numpy twin on the same inputs. On a
machine where no GPU context can be made at all, the tests skip and say why.
"""
import importlib

import pytest

from blender_support import clean_scene, visibake  # noqa: F401


@pytest.fixture(scope="session")
def gpu_shaders(visibake):
    shaders = importlib.import_module(f"{visibake.__name__}.gpu_shaders")
    runtime = shaders.runtime
    try:
        info = runtime.device_info()
    except runtime.GPUUnavailable as error:
        pytest.skip(f"no GPU context on this machine: {error}")
    print(f"\nGPU: {info.backend}, {info.renderer} ({info.vendor}, {info.version})")
    return shaders
