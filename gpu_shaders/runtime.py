"""The GPU side's plumbing: a context in background mode, device facts, shaders, textures.

Facts this relies on (DESIGN.md, re-checked with bpy 5.0.1 on Mesa llvmpipe):

- In background mode the gpu module has no context until a render engine with
  ``bl_use_gpu_context`` renders once; a do-nothing engine on a 4 x 4 temporary scene
  makes one in ~0.1-0.3 s, and it then lasts for the session.
- Uploads take FLOAT buffers only; ``gpu.types.Buffer('FLOAT', n, array)`` wraps a
  contiguous float32 numpy array without copying (keep the array alive). Integers are
  sent as exact floats (< 2^24).
- ``GPUTexture.read()`` returns layer 0 of an array texture only; other layers are
  copied to a 2D texture by a compute pass first. A read buffer's numpy view has
  permuted strides: ``ravel(order="K")`` gives the memory order, (height, width, channels).
- Compile errors raise a bare Exception and print the GLSL log to stdout.
"""
from __future__ import annotations

import contextlib
import glob
import os
import sys
import time
from dataclasses import dataclass

import numpy as np

from ..core.errors import DeviceError

SHADER_FOLDER = os.path.dirname(os.path.abspath(__file__))
# Renderers that draw on the CPU: there the numpy twin of every pass is faster
# (DESIGN.md: a 1024^2 x 64 gather took ~1.9 s on llvmpipe against ~1.1 s in numpy).
SOFTWARE_RENDERERS = ("llvmpipe", "softpipe", "swrast", "software rasterizer", "microsoft basic render")
# The files a Linux process reaches a GPU through: DRM nodes (Mesa's drivers, virtio, NVIDIA with
# nvidia-drm), NVIDIA's own nodes, and WSL's paravirtualised GPU. With none of them, any context
# would be a software renderer.
GPU_DEVICE_FILES = ("/dev/dri/renderD*", "/dev/dri/card*", "/dev/nvidia[0-9]*", "/dev/dxg")
MAX_TEXTURE_SIZE = 16384
MAX_LAYERS = 2048
_ENGINE_ID = "VISIBAKE_GPU_CONTEXT"


class GPUUnavailable(RuntimeError):
    """No GPU context could be made (no display, no driver); the message says why."""


@dataclass
class DeviceInfo:
    backend: str
    renderer: str
    vendor: str
    version: str
    software: bool

    def as_dict(self) -> dict:
        return {"backend": self.backend, "renderer": self.renderer, "vendor": self.vendor,
                "version": self.version, "software": self.software}


def _context_engine():
    import bpy

    class VisiBakeGPUContext(bpy.types.RenderEngine):
        """Renders nothing: rendering once with it gives background Blender a GPU context."""

        bl_idname = _ENGINE_ID
        bl_label = "VisiBake GPU context"
        bl_use_gpu_context = True

        def render(self, depsgraph):
            pass

    return VisiBakeGPUContext


_context_ready = False
_context_error: str | None = None


@contextlib.contextmanager
def _quiet_native_stderr():
    """Silence what the GL/EGL libraries print while probing for a context.

    Mesa reports the EGL configurations it rejects on the way (EGL_BAD_MATCH) even when
    a context is then made; a user reading the command's output would take them for
    errors. Failures still surface, as the exception from the probe.
    """
    try:
        saved = os.dup(2)
    except OSError:
        yield
        return
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 2)
            try:
                yield
            finally:
                os.dup2(saved, 2)
    finally:
        os.close(saved)


def ensure_context() -> None:
    """Make sure the gpu module can run compute shaders (creating a context if needed).

    Raises GPUUnavailable when there is no way to get one (and keeps saying so for the
    rest of the session without probing again). Leaves no datablock behind.
    """
    global _context_ready, _context_error
    if _context_ready:
        return
    if _context_error is not None:
        raise GPUUnavailable(_context_error)
    import bpy

    if not bpy.app.background:
        _context_ready = True  # the UI has its own context
        return
    engine = _context_engine()
    registered = False
    scene = camera = camera_data = None
    images_before = set(bpy.data.images)
    try:
        bpy.utils.register_class(engine)
        registered = True
        scene = bpy.data.scenes.new("VisiBake GPU context")
        scene.render.engine = _ENGINE_ID
        scene.render.resolution_x = scene.render.resolution_y = 4
        camera_data = bpy.data.cameras.new("VisiBake GPU context")
        camera = bpy.data.objects.new("VisiBake GPU context", camera_data)
        scene.collection.objects.link(camera)
        scene.camera = camera
        with _quiet_native_stderr():
            bpy.ops.render.render(scene=scene.name)
        import gpu

        gpu.platform.backend_type_get()
    except Exception as error:  # noqa: BLE001  (any failure means: no GPU here)
        _context_error = f"no GPU context in background mode ({type(error).__name__}: {error})"
        raise GPUUnavailable(_context_error) from None
    finally:
        for block, collection in ((camera, bpy.data.objects), (camera_data, bpy.data.cameras),
                                  (scene, bpy.data.scenes)):
            if block is not None:
                collection.remove(block)
        for image in set(bpy.data.images) - images_before:  # the render result of the probe
            bpy.data.images.remove(image)
        if registered:
            bpy.utils.unregister_class(engine)
    _context_ready = True


def device_info() -> DeviceInfo:
    ensure_context()
    import gpu

    renderer = gpu.platform.renderer_get()
    return DeviceInfo(backend=str(gpu.platform.backend_type_get()), renderer=renderer,
                      vendor=gpu.platform.vendor_get(), version=gpu.platform.version_get(),
                      software=any(name in renderer.lower() for name in SOFTWARE_RENDERERS))


def gpu_device_files() -> list[str] | None:
    """On Linux, the device files of :data:`GPU_DEVICE_FILES` present (empty: no GPU to reach);
    elsewhere None (not known without a context)."""
    if not sys.platform.startswith("linux"):
        return None
    return sorted(path for pattern in GPU_DEVICE_FILES for path in glob.glob(pattern))


def choose_device(requested: str) -> tuple[str, str, DeviceInfo | None]:
    """('gpu' or 'cpu', the reason, device facts or None) for 'auto', 'gpu' or 'cpu'.

    'gpu' raises GPUUnavailable if there is no context; 'auto' falls back to the CPU
    then, and on software renderers, where the CPU kernels are faster. On a Linux machine with
    no GPU device file, 'auto' picks the CPU without making a context: in background mode a
    context costs 0.1-0.3 s and about 96 MiB that the bake would carry to its end, only to learn
    that the renderer is llvmpipe (docs/benchmarks.md, speed part 17).
    """
    if requested == "cpu":
        return "cpu", "asked for", None
    if requested == "auto" and gpu_device_files() == []:
        return "cpu", "auto: no GPU device on this machine (none of " + ", ".join(GPU_DEVICE_FILES) + ")", None
    try:
        info = device_info()
    except GPUUnavailable as error:
        if requested == "gpu":
            raise
        return "cpu", f"auto: {error}", None
    if requested == "gpu":
        return "gpu", "asked for", info
    if info.software:
        return "cpu", f"auto: {info.renderer} renders on the CPU, where the CPU kernels are faster", info
    return "gpu", f"auto: {info.renderer}", info


_shaders: dict = {}


def shader(name: str, build):
    """The compiled compute shader ``name``, built on first use by ``build(info)``.

    ``build`` receives a fresh GPUShaderCreateInfo to declare resources on; the
    source is ``<name>.glsl`` beside this file.
    """
    if name in _shaders:
        return _shaders[name]
    ensure_context()
    import gpu

    with open(os.path.join(SHADER_FOLDER, f"{name}.glsl"), encoding="utf-8") as handle:
        source = handle.read()
    info = gpu.types.GPUShaderCreateInfo()
    build(info)
    info.compute_source(source)
    started = time.perf_counter()
    try:
        compiled = gpu.shader.create_from_info(info)
    except Exception as error:  # noqa: BLE001  (the gpu module raises a bare Exception)
        raise RuntimeError(f"GLSL shader {name}.glsl did not compile (the log is on stdout): {error}") from None
    _shaders[name] = compiled
    compile_seconds[name] = time.perf_counter() - started
    return compiled


compile_seconds: dict[str, float] = {}


def float_texture(array: np.ndarray, layers: bool = False):
    """A GPUTexture holding ``array``.

    array : (H, W, C) or, with ``layers``, (L, H, W, C) float-convertible, C in 1, 2, 4
    Returns (texture, the float32 array it was made from; keep it alive while used).
    """
    import gpu

    data = np.ascontiguousarray(array, np.float32)
    channels = data.shape[-1]
    fmt = {1: "R32F", 2: "RG32F", 4: "RGBA32F"}[channels]
    height, width = data.shape[-3], data.shape[-2]
    if width > MAX_TEXTURE_SIZE or height > MAX_TEXTURE_SIZE:
        raise DeviceError(f"texture {width}x{height} exceeds the GPU limit of {MAX_TEXTURE_SIZE}; use the CPU device")
    buffer = gpu.types.Buffer("FLOAT", data.size, data.ravel())
    if layers:
        if data.shape[0] > MAX_LAYERS:
            raise DeviceError(f"{data.shape[0]} layers exceed the GPU limit of {MAX_LAYERS}; use the CPU device")
        texture = gpu.types.GPUTexture((width, height), layers=data.shape[0], format=fmt, data=buffer)
    else:
        texture = gpu.types.GPUTexture((width, height), format=fmt, data=buffer)
    return texture, data


class TextureSet:
    """The textures of one pass: uploaded arrays stay alive with them, all freed together.

    Use as a context manager; dropping the last reference frees a GPUTexture, so on
    leaving the block (normally or by an exception) nothing of the pass stays on the GPU.
    """

    def __init__(self):
        self._textures = []
        self._arrays = []
        self._copy_target = None

    def upload(self, array: np.ndarray, layers: bool = False):
        made, data = float_texture(array, layers)
        self._textures.append(made)
        self._arrays.append(data)
        return made

    def empty(self, width: int, height: int, layers: int = 0, fmt: str = "RGBA32F"):
        made = empty_texture(width, height, layers, fmt)
        self._textures.append(made)
        return made

    @property
    def uploaded_bytes(self) -> int:
        return sum(array.nbytes for array in self._arrays)

    def __enter__(self) -> "TextureSet":
        return self

    def __exit__(self, *exc) -> None:
        self._textures.clear()
        self._arrays.clear()
        self._copy_target = None


def empty_texture(width: int, height: int, layers: int = 0, fmt: str = "RGBA32F"):
    import gpu

    if layers:
        return gpu.types.GPUTexture((width, height), layers=layers, format=fmt)
    return gpu.types.GPUTexture((width, height), format=fmt)


def read_texture(texture) -> np.ndarray:
    """(H, W, C) float32 copy of a 2D texture (layer 0 of an array texture)."""
    buffer = texture.read()
    # The buffer's numpy view has permuted strides; memory order is (H, W, C).
    return np.array(np.asarray(buffer).ravel(order="K"), np.float32).reshape(buffer.dimensions)


COPY_GROUP_SIZE = 16


def _build_copy(info) -> None:
    info.image(0, "RGBA32F", "FLOAT_2D", "target", qualifiers={"WRITE"})
    info.sampler(0, "FLOAT_2D_ARRAY", "source")
    info.push_constant("INT", "layer")
    info.local_group_size(COPY_GROUP_SIZE, COPY_GROUP_SIZE)


def read_layer(resident: TextureSet, texture, layer: int, width: int, height: int) -> np.ndarray:
    """(height, width, 4) float32 copy of one layer of an RGBA32F array texture.

    Layer 0 is read directly; the others go through copy_layer.glsl into a 2D texture
    (made once per TextureSet), since ``read()`` returns layer 0 only.
    """
    if layer == 0:
        return read_texture(texture)
    import gpu

    if getattr(resident, "_copy_target", None) is None or resident._copy_target[1] != (width, height):
        resident._copy_target = (resident.empty(width, height), (width, height))
    target = resident._copy_target[0]
    copy = shader("copy_layer", _build_copy)
    copy.bind()
    copy.image("target", target)
    copy.uniform_sampler("source", texture)
    copy.uniform_int("layer", layer)
    gpu.compute.dispatch(copy, -(-width // COPY_GROUP_SIZE), -(-height // COPY_GROUP_SIZE), 1)
    return read_texture(target)


def sample_grid(count: int, width: int = 2048) -> tuple[int, int]:
    """A 2D layout (width, height) for ``count`` samples in row-major order."""
    width = max(1, min(width, count))
    height = max(1, -(-count // width))
    if height > MAX_TEXTURE_SIZE:
        raise DeviceError(f"{count} samples do not fit a {MAX_TEXTURE_SIZE}^2 texture; use the CPU device")
    return width, height


def to_grid(values: np.ndarray, width: int, height: int) -> np.ndarray:
    """Per-sample rows (K, C) as a (height, width, C) image, zero-padded."""
    values = np.asarray(values, np.float32)
    if values.ndim == 1:
        values = values[:, None]
    grid = np.zeros((height * width, values.shape[1]), np.float32)
    grid[:len(values)] = values
    return grid.reshape(height, width, values.shape[1])
