"""Scene packages (core.distributed.package): a bake's inputs in one checked file, read back without Blender."""
import json
import math
import os
import struct
import subprocess
import sys
import tomllib
import zipfile
from dataclasses import fields, is_dataclass
from pathlib import Path

import numpy as np
import pytest

from core.distributed import package as package_module
from core.distributed.package import FORMAT_VERSION, PackageRefused, manifest_checksum, read_package, write_package
from core.errors import BakeRefused
from core.pipeline.relight import bake
from core.scene import Light, Material, Scene, World
from core.settings import BakeSettings
from core.version import visibake_version
from core_scenes import grid_mesh, quad_mesh

ROOT = Path(__file__).resolve().parents[2]


def _rotation_z(angle):
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _full_scene() -> Scene:
    """Every kind of value a scene holds: an atlas and a vertex mesh, textured and plain
    materials, lamps of every kind (linking tuples, empty and None), a world image and suns."""
    rng = np.random.default_rng(7)
    painted = Material(name="Painted", base_color=np.array([0.2, 0.4, 0.6]),
                       base_color_texture=rng.random((4, 5, 3), dtype=np.float32), texture_uv_map="UVMap",
                       emission=np.array([0.0, 0.5, 1.5]))
    plain = Material(name="Plain", base_color=np.full(3, 0.5, np.float32))
    ground = quad_mesh("Ground", [(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)], material=painted, resolution=16)
    ground.materials.append(plain)
    ground.material_index = np.array([0, 1], np.int32)
    ground.uv_maps["Second"] = np.asfortranarray(rng.random((2, 3, 2)).astype(np.float32))
    ground.light_group, ground.casts_shadow, ground.terminator_offset = "floor", False, 0.0
    ground.corner_loops = np.arange(6, dtype=np.int64).reshape(2, 3)
    grid = grid_mesh("Grid", size=0.5, segments=3, z=0.4, material=plain, flip=True)
    grid.output = False
    lights = [
        Light("Sun", "SUN", np.ones(3), 3.0, direction=np.array([0.3, 0.0, -1.0]) / np.hypot(0.3, 1.0), angle=0.05),
        Light("Bulb", "POINT", np.array([1.0, 0.8, 0.6]), np.float64(150.0), position=np.array([0.5, 0.2, 1.2]),
              radius=0.1, sphere=True, receivers=("Ground",)),
        Light("Spot", "SPOT", np.array([0.9, 0.9, 1.0]), 80.0, position=np.array([0.0, 0.0, 2.0]), spot_size=0.7,
              spot_blend=0.3, casts_shadows=False, blockers=("Grid", "Ground")),
        Light("Panel", "AREA", np.ones(3), 40.0, position=np.array([0.0, 1.0, 1.5]), area_shape="ELLIPSE",
              size_x=np.float64(0.5), size_y=np.float32(0.25), axis_x=np.array([0.0, 1.0, 0.0]),
              axis_y=np.array([-1.0, 0.0, 0.0]), group="panels", receivers=(), blockers=()),
    ]
    sky_sun = Light("SkySun", "SUN", np.array([1.0, 0.9, 0.8]), 5.0, direction=np.array([0.0, 0.6, -0.8]),
                    angle=0.01)
    world = World(color=np.array([0.1, 0.2, 0.3]), image=rng.random((8, 16, 3), dtype=np.float32),
                  rotation=_rotation_z(0.3), light_group="sky", suns=[sky_sun])
    return Scene([ground, grid], lights, world)


NON_DEFAULT_SETTINGS = BakeSettings(
    directions=24, bounces=3, shadows="fractions", shadow_regions=7, rotate=True, seed=5, interleave=2,
    passes=("lighting", "ao"), margin=2, area_light_samples=3, footprint_samples=4, sharp_contacts=False,
    stitch_seams=False, emitter_samples=5, threads=1, chunk_rays=1000, light_groups=True, vertex_lookup="nearest")


def _assert_identical(expected, actual, path="value"):
    """The same types, values and (for arrays) dtype, shape and bytes, all the way down."""
    assert type(actual) is type(expected), f"{path}: {type(actual)} != {type(expected)}"
    if isinstance(expected, np.ndarray):
        assert actual.dtype == expected.dtype and actual.shape == expected.shape, path
        assert actual.tobytes() == expected.tobytes(), path
    elif isinstance(expected, np.generic):
        assert actual.dtype == expected.dtype and actual.tobytes() == expected.tobytes(), path
    elif is_dataclass(expected):
        for field in fields(expected):
            _assert_identical(getattr(expected, field.name), getattr(actual, field.name), f"{path}.{field.name}")
    elif isinstance(expected, (list, tuple)):
        assert len(actual) == len(expected), path
        for i, (a, b) in enumerate(zip(expected, actual)):
            _assert_identical(a, b, f"{path}[{i}]")
    elif isinstance(expected, dict):
        assert list(actual) == list(expected), f"{path}: keys or their order differ"
        for key in expected:
            _assert_identical(expected[key], actual[key], f"{path}[{key!r}]")
    elif isinstance(expected, float):
        same_bits = struct.pack("<d", actual) == struct.pack("<d", expected)
        assert same_bits or (math.isnan(actual) and math.isnan(expected)), path
    else:
        assert actual == expected, path


def test_round_trip_keeps_every_field_dtype_shape_and_byte(tmp_path):
    scene = _full_scene()
    path = tmp_path / "scene.vbpkg"
    checksum = write_package(path, scene, NON_DEFAULT_SETTINGS, extra={"job": "tile-3", "frame": 12})
    loaded = read_package(path)
    _assert_identical(scene, loaded.scene, "scene")
    _assert_identical(NON_DEFAULT_SETTINGS, loaded.settings, "settings")
    assert loaded.settings == NON_DEFAULT_SETTINGS and loaded.settings != BakeSettings()
    assert loaded.extra == {"job": "tile-3", "frame": 12}
    assert loaded.checksum == checksum and len(checksum) == 64
    assert loaded.visibake_version == visibake_version() and loaded.format_version == FORMAT_VERSION == 1
    # Layout kept too, not only values: a Fortran-ordered array comes back Fortran-ordered.
    assert loaded.scene.meshes[0].uv_maps["Second"].flags.f_contiguous
    assert type(loaded.scene.lights[1].strength) is np.float64 and type(loaded.scene.lights[0].strength) is float
    assert loaded.scene.lights[3].receivers == () and loaded.scene.lights[0].receivers is None
    with zipfile.ZipFile(path) as archive:
        kinds = {info.filename: info.compress_type for info in archive.infolist()}
        manifest = json.loads(archive.read("manifest.json"))
    assert kinds.pop("manifest.json") == zipfile.ZIP_DEFLATED
    assert kinds and set(kinds.values()) == {zipfile.ZIP_STORED}
    assert all(name.startswith("arrays/") and name.endswith(".npy") for name in kinds)
    assert manifest["format"] == "visibake-scene-package" and manifest["created"].endswith("+00:00")
    assert manifest["checksum"] == checksum == manifest_checksum(manifest)


def test_values_of_extra_round_trip_exactly(tmp_path):
    shared = np.arange(6, dtype=np.uint16).reshape(2, 3)
    extra = {"z": -0.0, "nan": math.nan, "inf": math.inf, "-inf": -math.inf, "tenth": 0.1, "big": 2**70,
             "f32": np.float32(0.1), "nan32": np.frombuffer(b"\x01\x00\xc0\x7f", np.float32)[0],
             "i64": np.int64(-3), "flag": np.bool_(True), "c": np.complex64(1 - 2j), "text": "Grüße ✓",
             "nested": [(1, [2.5, None]), {"b": True, "a": False}], "empty": {}, "a0": np.array(3.5),
             "none": np.zeros((0, 3), np.float32), "names": np.array(["ab", "c"]), "same": [shared, shared]}
    write_package(tmp_path / "p", Scene([], []), BakeSettings(), extra)
    loaded = read_package(tmp_path / "p").extra
    _assert_identical(extra, loaded, "extra")
    assert list(loaded["nested"][1]) == ["b", "a"]  # insertion order, not sorted
    # One array object met twice is stored once and read back as one object.
    assert loaded["same"][0] is loaded["same"][1]
    assert read_package(_written(tmp_path / "q")).extra is None


def _written(path, scene=None, settings=None, extra=None):
    write_package(path, scene or Scene([quad_mesh("Q", [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)])], []),
                  settings or BakeSettings(), extra)
    return path


def test_the_checksum_names_the_content(tmp_path):
    first = write_package(tmp_path / "a", _full_scene(), NON_DEFAULT_SETTINGS)
    again = write_package(tmp_path / "b", _full_scene(), NON_DEFAULT_SETTINGS)
    other = write_package(tmp_path / "c", _full_scene(), BakeSettings(directions=25))
    assert first == again != other


class _Unknown:
    pass


@pytest.mark.parametrize("extra, place", [
    ({"s": {1, 2}}, "extra['s']"),
    ({"deep": [1, (2, _Unknown())]}, r"extra['deep'][1][1]"),
    ({"keys": {1: "a"}}, "extra['keys']"),
    ({"objects": np.array([None, 1], object)}, "extra['objects']"),
    ({"masked": np.ma.masked_array([1.0, 2.0], mask=[0, 1])}, "extra['masked']"),
    ({"when": np.datetime64("2024-01-01")}, "extra['when']"),
    ({"call": len}, "extra['call']"),
])
def test_values_a_package_cannot_hold_raise_type_error_naming_the_place(tmp_path, extra, place):
    with pytest.raises(TypeError) as raised:
        write_package(tmp_path / "p", Scene([], []), BakeSettings(), extra)
    assert str(raised.value).startswith(place + ":")
    assert not os.listdir(tmp_path)


def test_a_callable_in_the_scene_is_named_by_its_field(tmp_path):
    scene = _full_scene()
    scene.lights[2].name = lambda: "x"
    with pytest.raises(TypeError, match=r"^scene\.lights\[2\]\.name: .*function"):
        write_package(tmp_path / "p", scene, BakeSettings())


def test_a_failed_write_leaves_the_file_that_was_there(tmp_path, monkeypatch):
    path = _written(tmp_path / "scene.vbpkg")
    before = path.read_bytes()
    calls = []

    def failing_save(*args, **kwargs):
        calls.append(1)
        if len(calls) == 3:
            raise OSError("disk full")
        return real_save(*args, **kwargs)

    real_save = np.save
    monkeypatch.setattr(np, "save", failing_save)
    with pytest.raises(OSError, match="disk full"):
        write_package(path, _full_scene(), NON_DEFAULT_SETTINGS)
    assert path.read_bytes() == before and os.listdir(tmp_path) == ["scene.vbpkg"]


# Refusals.

def _rewrite(source: Path, target: Path, manifest_edit=None, entry_edits=None, rechecksum=True) -> Path:
    """A copy of the package at ``source`` with its manifest (a function of the dict) or entries
    (name -> new bytes) changed; a consistent ZIP, its checksum recomputed unless told not to."""
    with zipfile.ZipFile(source) as archive:
        contents = {info.filename: (info, archive.read(info.filename)) for info in archive.infolist()}
    manifest = json.loads(contents["manifest.json"][1])
    if manifest_edit is not None:
        manifest_edit(manifest)
        if rechecksum:
            manifest["checksum"] = manifest_checksum(manifest)
    contents["manifest.json"] = (contents["manifest.json"][0], json.dumps(manifest).encode())
    for name, data in (entry_edits or {}).items():
        contents[name] = (contents[name][0], data)
    with zipfile.ZipFile(target, "w") as archive:
        for info, data in contents.values():
            archive.writestr(info, data)
    return target


def _first_array_bytes(path: Path) -> bytes:
    with zipfile.ZipFile(path) as archive:
        return archive.read("arrays/0.npy")


def test_a_changed_array_is_refused_by_its_digest(tmp_path):
    path = _written(tmp_path / "p")
    data = bytearray(_first_array_bytes(path))
    data[-1] ^= 0x01
    changed = _rewrite(path, tmp_path / "changed", entry_edits={"arrays/0.npy": bytes(data)})
    with pytest.raises(PackageRefused, match=r"arrays/0\.npy does not match its blake2b digest"):
        read_package(changed)


def test_a_flipped_byte_in_the_file_is_refused(tmp_path):
    path = _written(tmp_path / "p")
    raw = bytearray(path.read_bytes())
    with zipfile.ZipFile(path) as archive:
        info = archive.getinfo("arrays/0.npy")
    # The entry's data follows its 30-byte local header, file name and extra field.
    name_length, extra_length = struct.unpack("<HH", raw[info.header_offset + 26:info.header_offset + 30])
    start = info.header_offset + 30 + name_length + extra_length
    raw[start + info.file_size - 1] ^= 0x80
    path.write_bytes(bytes(raw))
    # Caught by the archive's CRC-32 before the digest is even compared; either way, refused.
    with pytest.raises(PackageRefused, match=r"arrays/0\.npy"):
        read_package(path)


def test_an_edited_tree_is_refused_by_the_checksum(tmp_path):
    path = _written(tmp_path / "p")

    def more_directions(manifest):
        manifest["tree"]["settings"]["fields"]["directions"] = 129

    changed = _rewrite(path, tmp_path / "changed", more_directions, rechecksum=False)
    with pytest.raises(PackageRefused, match="does not match its checksum"):
        read_package(changed)


def test_a_newer_format_is_refused_as_newer(tmp_path):
    changed = _rewrite(_written(tmp_path / "p"), tmp_path / "changed",
                       lambda manifest: manifest.update(format_version=2))
    with pytest.raises(PackageRefused, match="written by a newer VisiBake .*format 2"):
        read_package(changed)
    older = _rewrite(_written(tmp_path / "p"), tmp_path / "older", lambda manifest: manifest.update(format_version=0))
    with pytest.raises(PackageRefused, match="format 0 is not one this VisiBake reads"):
        read_package(older)


def test_another_visibake_version_is_refused_naming_both(tmp_path):
    changed = _rewrite(_written(tmp_path / "p"), tmp_path / "changed",
                       lambda manifest: manifest.update(visibake_version="99.1.0"))
    with pytest.raises(PackageRefused) as raised:
        read_package(changed)
    assert "99.1.0" in str(raised.value) and f"this is VisiBake {visibake_version()}" in str(raised.value)


def test_a_file_that_is_not_a_package_is_refused(tmp_path):
    text = tmp_path / "notes.txt"
    text.write_text("not a zip")
    with pytest.raises(PackageRefused, match="not a ZIP archive"):
        read_package(text)
    with zipfile.ZipFile(tmp_path / "other.zip", "w") as archive:
        archive.writestr("readme.txt", "hello")
    with pytest.raises(PackageRefused, match="no manifest.json"):
        read_package(tmp_path / "other.zip")
    wrong = _rewrite(_written(tmp_path / "p"), tmp_path / "wrong", lambda manifest: manifest.update(format="x"))
    with pytest.raises(PackageRefused, match="not a VisiBake scene package"):
        read_package(wrong)
    with pytest.raises(PackageRefused, match="cannot read"):
        read_package(tmp_path / "missing.vbpkg")
    assert issubclass(PackageRefused, BakeRefused)


def test_an_unknown_class_is_refused_without_importing_it(tmp_path):
    def foreign(manifest):
        manifest["tree"]["settings"]["class"] = "os.system"

    changed = _rewrite(_written(tmp_path / "p"), tmp_path / "changed", foreign)
    with pytest.raises(PackageRefused, match=r"settings: unknown class 'os\.system'"):
        read_package(changed)


def test_an_entry_the_manifest_does_not_list_is_refused(tmp_path):
    path = _written(tmp_path / "p")
    with zipfile.ZipFile(path, "a") as archive:
        archive.writestr("arrays/99.npy", b"")
    with pytest.raises(PackageRefused, match=r"unexpected \['arrays/99\.npy'\]"):
        read_package(path)


# Baking what was read.

def _bake_scene() -> Scene:
    rng = np.random.default_rng(3)
    ground = quad_mesh("Ground", [(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)],
                       material=Material(base_color=np.full(3, 0.7), base_color_texture=rng.random(
                           (4, 4, 3), dtype=np.float32), texture_uv_map="UVMap"), resolution=12)
    roof = quad_mesh("Roof", [(-0.4, -0.4, 0.6), (-0.4, 0.4, 0.6), (0.4, 0.4, 0.6), (0.4, -0.4, 0.6)],
                     material=Material(base_color=np.full(3, 0.5), emission=np.array([0.2, 0.1, 0.0])), resolution=8)
    grid = grid_mesh("Grid", size=0.4, segments=2, z=0.2, material=Material(base_color=np.full(3, 0.6)))
    lights = [Light("Sun", "SUN", np.ones(3), 3.0, direction=np.array([0.3, 0.0, -1.0]) / np.hypot(0.3, 1.0)),
              Light("Lamp", "POINT", np.array([1.0, 0.8, 0.6]), 150.0, position=np.array([0.5, 0.2, 1.2]),
                    receivers=("Ground", "Grid"))]
    world = World(color=np.full(3, 0.2), image=rng.random((4, 8, 3), dtype=np.float32), rotation=_rotation_z(0.5))
    return Scene([ground, roof, grid], lights, world)


def test_baking_the_read_package_gives_the_same_bits(tmp_path):
    scene = _bake_scene()
    settings = BakeSettings(directions=16, bounces=1, passes=("lighting", "direct", "indirect", "ao"), margin=1)
    write_package(tmp_path / "p", scene, settings)
    loaded = read_package(tmp_path / "p")
    original, again = bake(scene, settings), bake(loaded.scene, loaded.settings)
    assert [o.name for o in again.objects] == [o.name for o in original.objects] == ["Ground", "Roof", "Grid"]
    assert original.objects[2].domain is not None  # the grid's vertex tables were baked too
    assert all(np.any(o.images["lighting"][..., :3] > 0) for o in original.objects)
    for a, b in zip(original.objects, again.objects):
        assert (a.width, a.height, a.samples, a.domain) == (b.width, b.height, b.samples, b.domain)
        assert list(a.images) == list(b.images) == list(settings.passes)
        for name in settings.passes:
            assert a.images[name].dtype == b.images[name].dtype
            assert np.array_equal(a.images[name], b.images[name]), (a.name, name)
        assert (a.coarse_triangles is None) == (b.coarse_triangles is None)
        if a.coarse_triangles is not None:
            assert np.array_equal(a.coarse_triangles, b.coarse_triangles)


# Without Blender.

def test_a_worker_reads_a_package_without_blender(tmp_path):
    path = tmp_path / "scene.vbpkg"
    checksum = write_package(path, _full_scene(), NON_DEFAULT_SETTINGS)
    script = (f"import sys; sys.path.insert(0, {str(ROOT)!r})\n"
              "from core.distributed.package import read_package\n"
              f"package = read_package({str(path)!r})\n"
              "assert 'bpy' not in sys.modules, 'reading a package imported bpy'\n"
              "print(package.checksum, len(package.scene.meshes), package.settings.directions)\n")
    done = subprocess.run([sys.executable, "-c", script], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == [checksum, "2", "24"]


def test_the_version_is_the_manifests():
    with open(ROOT / "blender_manifest.toml", "rb") as stream:
        assert visibake_version() == tomllib.load(stream)["version"]
    assert package_module.visibake_version is visibake_version
