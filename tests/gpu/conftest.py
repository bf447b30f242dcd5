"""Fixtures for the GPU passes: the installed extension, and its gpu_shaders with a context.

Every test here compares a GPU pass with its numpy twin on the same inputs. On a
machine where no GPU context can be made at all, the tests skip and say why (under CI
they fail: llvmpipe gives a context there).
"""
import importlib

import pytest

from blender_support import clean_scene, gpu_runtime_or_skip, visibake  # noqa: F401


@pytest.fixture(scope="session")
def gpu_shaders(visibake):
    shaders = importlib.import_module(f"{visibake.__name__}.gpu_shaders")
    _, info = gpu_runtime_or_skip(visibake)
    print(f"\nGPU: {info.backend}, {info.renderer} ({info.vendor}, {info.version})")
    return shaders
