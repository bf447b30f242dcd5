"""Scene packages: one file with everything ``core.pipeline.relight.bake(scene, settings)`` needs,
for workers that run plain Python and numpy, without Blender.

What is in the file
-------------------
A ZIP archive of

    manifest.json     (deflated) what the package is, and the encoded scene, settings and extra
    arrays/<n>.npy    (stored: mostly incompressible floats) the n-th numpy array of the tree,
                      written by ``np.save(..., allow_pickle=False)``

manifest.json is one JSON object (ASCII, no NaN or Infinity tokens):

    format            "visibake-scene-package"
    format_version    1 (:data:`FORMAT_VERSION`)
    visibake_version  the writer's VisiBake (blender_manifest.toml's version); a reader refuses
                      any other, since a worker must bake exactly what the writer's VisiBake would
    created           when it was written, UTC ISO 8601
    tree              {"scene": node, "settings": node, "extra": node}
    arrays            per array n, in order: {"dtype": numpy's dtype.str such as "<f4",
                      "shape": [...], "blake2b": the hex blake2b-256 digest of the whole
                      arrays/<n>.npy entry, its .npy header included}
    checksum          see below

A node is JSON null, true or false, an integer, a finite float (JSON keeps a Python float
exactly: it is written as its repr, -0.0 included), a string, or an object with a "type":

    {"type": "float", "value": "nan" | "inf" | "-inf"}     a non-finite Python float (a NaN's
                                                            sign and payload are not kept)
    {"type": "numpy", "dtype": "<f8", "hex": "..."}         a numpy scalar: its dtype and its
                                                            bytes, every bit kept
    {"type": "array", "index": n}                           arrays/<n>.npy; an array object
                                                            met twice is stored once, and read
                                                            back as one object
    {"type": "list", "items": [node, ...]}
    {"type": "tuple", "items": [node, ...]}
    {"type": "dict", "items": [[key, node], ...]}           str keys, in insertion order
    {"type": "dataclass", "class": name, "fields": {field: node, ...}}

``name`` is a key of :data:`CLASSES` (the dataclasses of :mod:`core.scene` and
:class:`core.settings.BakeSettings`), and ``fields`` names every field of that class. Arrays
hold numbers, booleans or fixed-width strings (dtype kinds of :data:`ARRAY_KINDS`). Anything
else raises TypeError when written, naming where it is (``scene.meshes[0].materials[1].emission``):
a caller put it there, which is a bug, not the user's input.

The checksum
------------
``checksum`` is the hex blake2b digest (32 bytes) of the canonical JSON of the manifest's
``format``, ``format_version``, ``visibake_version``, ``tree`` and ``arrays``, that is of

    json.dumps({"arrays": ..., "format": ..., "format_version": ..., "tree": ..., "visibake_version": ...},
               sort_keys=True, separators=(",", ":"), ensure_ascii=True, allow_nan=False).encode("ascii")

(:func:`manifest_checksum`). ``arrays`` lists every array's digest in order, and each digest
covers every byte of its entry, so a change of any byte of the tree or of any array changes
the checksum. ``created`` is left out, so that the same inputs written by the same VisiBake
get the same checksum: a worker can name what it was given, and keep results, by it.

A reader checks, in this order: a ZIP with a manifest; the format, its version (a newer one
may define all of the rest differently) and VisiBake's version; the checksum; the archive's
entries; each array's digest (before numpy parses a byte of it), dtype and shape; and then
builds the objects, refusing a class outside :data:`CLASSES`. Every refusal is a
:class:`PackageRefused` (a :class:`core.errors.BakeRefused`: exit status 2).

Why not pickle
--------------
A package crosses machines. Unpickling runs whatever code the file names, so a damaged or
forged package would run code on every worker that opened it; this format only ever builds
the registered dataclasses, numpy arrays and JSON values, and ``np.load`` reads the arrays
with ``allow_pickle=False``. It also stays readable by other tools (JSON and .npy).
"""
from __future__ import annotations

import hashlib
import json
import math
import os
import tempfile
import zipfile
import zlib
from dataclasses import dataclass, fields
from datetime import datetime, timezone

import numpy as np

from ..errors import BakeRefused
from ..outputs.atomic import atomic_file
from ..scene import Light, Material, Mesh, Scene, World
from ..settings import BakeSettings
from ..version import visibake_version

FORMAT_NAME = "visibake-scene-package"
FORMAT_VERSION = 1
MANIFEST_NAME = "manifest.json"
# The only classes a package builds; a name from the file is looked up here and nowhere else.
CLASSES = {cls.__name__: cls for cls in (Scene, Mesh, Material, Light, World, BakeSettings)}
_CLASS_NAMES = {cls: name for name, cls in CLASSES.items()}
# Booleans, integers, floats, complex numbers and fixed-width strings: .npy stores them without pickle.
ARRAY_KINDS = "biufcSU"
# What the checksum covers: all of the manifest but the time it was written and the checksum itself.
CHECKSUMMED = ("format", "format_version", "visibake_version", "tree", "arrays")
_MANIFEST_KEYS = frozenset(CHECKSUMMED + ("created", "checksum"))
_TREE_KEYS = frozenset(("scene", "settings", "extra"))
_NON_FINITE = {"nan": math.nan, "inf": math.inf, "-inf": -math.inf}
_NODE_KEYS = {
    "float": frozenset(("type", "value")),
    "numpy": frozenset(("type", "dtype", "hex")),
    "array": frozenset(("type", "index")),
    "list": frozenset(("type", "items")),
    "tuple": frozenset(("type", "items")),
    "dict": frozenset(("type", "items")),
    "dataclass": frozenset(("type", "class", "fields")),
}
_DIGEST_BYTES = 32
_READ_CHUNK = 1 << 20
# Room for a .npy header: an entry that may pass 2 GiB with it needs ZIP64 from its start.
_NPY_HEADER_ROOM = 1 << 16


# What zipfile raises for a damaged archive besides BadZipFile: a flipped byte in a header
# names an unknown compression method, version or flag (NotImplementedError), or the
# encryption flag (RuntimeError: a password is needed); in deflated data it breaks the stream
# (zlib.error); a cut file ends early (EOFError).
DAMAGED_ARCHIVE_ERRORS = (zipfile.BadZipFile, zipfile.LargeZipFile, OSError, EOFError, zlib.error, NotImplementedError,
                    RuntimeError)


class PackageRefused(BakeRefused):
    """A file that is not a scene package this VisiBake can bake: not a package, another
    format or VisiBake version, or damaged or changed since it was written; the message says which."""


@dataclass(frozen=True)
class Package:
    """A scene package as read back.

    scene, settings : what ``core.pipeline.relight.bake`` takes, every array with the dtype,
        shape and bytes it was written with
    extra : the writer's own dict (str keys), or None
    checksum : the package's checksum (hex blake2b-256, see the module's docstring)
    visibake_version : the VisiBake that wrote it (always this one: any other is refused)
    format_version : FORMAT_VERSION
    created : when it was written, UTC ISO 8601
    """

    scene: Scene
    settings: BakeSettings
    extra: dict | None
    checksum: str
    visibake_version: str
    format_version: int
    created: str


def manifest_checksum(manifest: dict) -> str:
    """The hex blake2b-256 digest of the canonical JSON of ``manifest``'s :data:`CHECKSUMMED` keys.

    Raises ValueError where they hold a float JSON cannot write (NaN, infinity)."""
    covered = {key: manifest[key] for key in CHECKSUMMED}
    canonical = json.dumps(covered, sort_keys=True, separators=(",", ":"), ensure_ascii=True, allow_nan=False)
    return hashlib.blake2b(canonical.encode("ascii"), digest_size=_DIGEST_BYTES).hexdigest()


# Writing.

def write_package(path: str | os.PathLike, scene: Scene, settings: BakeSettings, extra: dict | None = None) -> str:
    """Write ``scene``, ``settings`` and ``extra`` to a scene package at ``path``; return its checksum (hex).

    The file appears whole or not at all: it is written beside ``path`` and renamed over it.
    ``extra`` : None or a dict with str keys of the values a package holds (the module's docstring).
    Raises TypeError, naming the place, for a value a package cannot hold.
    """
    if type(scene) is not Scene:
        raise TypeError(f"scene: expected a core.scene.Scene, got {type(scene).__qualname__}")
    if type(settings) is not BakeSettings:
        raise TypeError(f"settings: expected a core.settings.BakeSettings, got {type(settings).__qualname__}")
    return _write(path, scene, settings, extra)


def write_values(path: str | os.PathLike, values: dict) -> str:
    """Write ``values`` (a dict of what a package holds) as a package with no scene and no
    settings (both null): what a render farm's steps exchange (core.distributed.farm), with
    the same checks and checksum as a scene package. Returns its checksum."""
    return _write(path, None, None, values)


def read_values(path: str | os.PathLike) -> dict:
    """The values :func:`write_values` wrote, checked as a package is; PackageRefused where the
    file is not one (a scene package included)."""
    where, _, scene, settings, extra = _read(path)
    if scene is not None or settings is not None or type(extra) is not dict:
        raise PackageRefused(f"{where} is not a VisiBake values file (it holds a scene or no values)")
    return extra


def _write(path, scene, settings, extra) -> str:
    if extra is not None and type(extra) is not dict:
        raise TypeError(f"extra: expected a dict or None, got {type(extra).__qualname__}")
    # The whole tree is encoded before the file is opened: a value that cannot be written is
    # found before anything is.
    encoder = _Encoder()
    tree = {"scene": encoder.encode(scene, "scene"), "settings": encoder.encode(settings, "settings"),
            "extra": encoder.encode(extra, "extra")}
    with atomic_file(os.fspath(path)) as stream, zipfile.ZipFile(stream, "w") as archive:
        entries = [_write_array(archive, index, array) for index, array in enumerate(encoder.arrays)]
        manifest = {"format": FORMAT_NAME, "format_version": FORMAT_VERSION, "visibake_version": visibake_version(),
                    "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
                    "tree": tree, "arrays": entries}
        manifest["checksum"] = manifest_checksum(manifest)
        text = json.dumps(manifest, indent=1, ensure_ascii=True, allow_nan=False)
        archive.writestr(_entry_info(MANIFEST_NAME, zipfile.ZIP_DEFLATED), text.encode("ascii"))
    return manifest["checksum"]


def package_bytes(scene: Scene, settings: BakeSettings, extra: dict | None = None) -> bytes:
    """The package :func:`write_package` writes, as bytes (what a cluster's workers are sent)."""
    with tempfile.TemporaryDirectory(prefix="visibake-package-") as folder:
        path = os.path.join(folder, "bake.vbpkg")
        write_package(path, scene, settings, extra)
        with open(path, "rb") as stream:
            return stream.read()


class _Encoder:
    """Values -> JSON nodes; the arrays met on the way are collected in ``arrays``, each object once."""

    def __init__(self):
        self.arrays: list[np.ndarray] = []
        # Keyed by id(): the arrays stay referenced in self.arrays, so no id is reused meanwhile.
        self._index_of: dict[int, int] = {}

    def encode(self, value, path: str):
        kind = type(value)
        # Exact types: a subclass (an IntEnum, a str subclass) would come back as its base.
        if value is None or kind in (bool, int, str):
            return value
        if kind is float:
            if math.isfinite(value):
                return value
            return {"type": "float", "value": "nan" if math.isnan(value) else ("inf" if value > 0 else "-inf")}
        if isinstance(value, np.ndarray):
            return self._array(value, path)
        if isinstance(value, np.generic):
            _check_dtype(value.dtype, path)
            return {"type": "numpy", "dtype": value.dtype.str, "hex": value.tobytes().hex()}
        if kind in (list, tuple):
            return {"type": kind.__name__, "items": [self.encode(item, f"{path}[{i}]") for i, item in enumerate(value)]}
        if kind is dict:
            items = []
            for key, item in value.items():
                if type(key) is not str:
                    raise TypeError(f"{path}: a scene package holds dicts with str keys only, got the key {key!r}")
                items.append([key, self.encode(item, f"{path}[{key!r}]")])
            return {"type": "dict", "items": items}
        name = _CLASS_NAMES.get(kind)
        if name is not None:
            return {"type": "dataclass", "class": name,
                    "fields": {f.name: self.encode(getattr(value, f.name), f"{path}.{f.name}") for f in fields(value)}}
        raise TypeError(f"{path}: a scene package cannot hold a {kind.__module__}.{kind.__qualname__} "
                        f"(it holds {', '.join(CLASSES)}, numpy arrays and scalars, None, bool, int, float, str, "
                        "lists, tuples and dicts with str keys)")

    def _array(self, array: np.ndarray, path: str) -> dict:
        # A masked array or matrix would come back as a plain array, its mask or semantics lost.
        if type(array) not in (np.ndarray, np.memmap):
            raise TypeError(f"{path}: a scene package holds plain numpy arrays, got a {type(array).__qualname__}")
        _check_dtype(array.dtype, path)
        index = self._index_of.get(id(array))
        if index is None:
            index = self._index_of[id(array)] = len(self.arrays)
            self.arrays.append(array)
        return {"type": "array", "index": index}


def _check_dtype(dtype: np.dtype, path: str) -> None:
    if dtype.kind not in ARRAY_KINDS or dtype.fields is not None or dtype.subdtype is not None:
        raise TypeError(f"{path}: a scene package holds numbers, booleans and strings, not dtype {dtype}")


class _HashingWriter:
    """A write-only stream that digests everything written through it."""

    def __init__(self, target, digest):
        self._target = target
        self._digest = digest

    def write(self, data) -> int:
        self._digest.update(data)
        return self._target.write(data)


def _entry_info(name: str, compression: int) -> zipfile.ZipInfo:
    # ZipInfo's fixed 1980 timestamp: the entries' bytes depend on their content only.
    info = zipfile.ZipInfo(name)
    info.compress_type = compression
    info.external_attr = 0o644 << 16  # rw-r--r-- where unzipped
    return info


def _write_array(archive: zipfile.ZipFile, index: int, array: np.ndarray) -> dict:
    """Stream ``array`` into arrays/<index>.npy, digesting it on the way; its manifest entry."""
    digest = hashlib.blake2b(digest_size=_DIGEST_BYTES)
    large = array.nbytes + _NPY_HEADER_ROOM >= zipfile.ZIP64_LIMIT
    with archive.open(_entry_info(f"arrays/{index}.npy", zipfile.ZIP_STORED), "w", force_zip64=large) as entry:
        # np.save writes to any object with write() in chunks: no copy of the whole array.
        np.save(_HashingWriter(entry, digest), array, allow_pickle=False)
    return {"dtype": array.dtype.str, "shape": list(array.shape), "blake2b": digest.hexdigest()}


# Reading.

def read_package(path: str | os.PathLike) -> Package:
    """Read the scene package at ``path``, checked whole (the module's docstring), without Blender.

    Raises :class:`PackageRefused` with the reason where it is not a package this VisiBake
    can bake.
    """
    where, manifest, scene, settings, extra = _read(path)
    for name, value, expected in (("scene", scene, Scene), ("settings", settings, BakeSettings)):
        if type(value) is not expected:
            raise PackageRefused(f"{where}: its {name} is a {type(value).__name__}, not a {expected.__name__}")
    if extra is not None and type(extra) is not dict:
        raise PackageRefused(f"{where}: its extra is a {type(extra).__name__}, not a dict")
    return Package(scene=scene, settings=settings, extra=extra, checksum=manifest["checksum"],
                   visibake_version=manifest["visibake_version"], format_version=manifest["format_version"],
                   created=manifest["created"])


def _read(path) -> tuple:
    """(where, manifest, scene, settings, extra) of the package at ``path``, checked whole."""
    where = os.fspath(path)
    try:
        archive = zipfile.ZipFile(where)
    except zipfile.BadZipFile:
        raise PackageRefused(f"{where} is not a VisiBake scene package (not a ZIP archive)") from None
    except OSError as error:
        raise PackageRefused(f"cannot read the scene package {where}: {error.strerror or error}") from None
    except (*DAMAGED_ARCHIVE_ERRORS, ValueError) as error:
        raise PackageRefused(f"{where} is damaged: its ZIP directory cannot be read ({error})") from None
    with archive:
        manifest = _read_manifest(archive, where)
        arrays = _read_arrays(archive, manifest["arrays"], where)
        decoder = _Decoder(arrays, where)
        tree = manifest["tree"]
        scene = decoder.decode(tree["scene"], "scene")
        settings = decoder.decode(tree["settings"], "settings")
        extra = decoder.decode(tree["extra"], "extra")
    return where, manifest, scene, settings, extra


def _refuse_constant(token: str):
    raise ValueError(f"{token} is not JSON")


def _read_manifest(archive: zipfile.ZipFile, where: str) -> dict:
    """The manifest, its format, versions and checksum checked, and its shape where the rest relies on it."""
    try:
        text = archive.read(MANIFEST_NAME)
    except KeyError:
        raise PackageRefused(f"{where} is not a VisiBake scene package (no {MANIFEST_NAME} in it)") from None
    except DAMAGED_ARCHIVE_ERRORS as error:
        raise PackageRefused(f"{where} is damaged: its {MANIFEST_NAME} cannot be read ({error})") from None
    try:
        manifest = json.loads(text.decode("ascii"), parse_constant=_refuse_constant)
    except ValueError as error:  # UnicodeDecodeError and JSONDecodeError are ValueErrors
        raise PackageRefused(f"{where} is damaged: its {MANIFEST_NAME} is not valid JSON ({error})") from None
    if type(manifest) is not dict or manifest.get("format") != FORMAT_NAME:
        found = manifest.get("format") if type(manifest) is dict else None
        raise PackageRefused(f"{where} is not a VisiBake scene package (format {found!r}, expected {FORMAT_NAME!r})")
    version = manifest.get("format_version")
    if type(version) is not int:
        raise PackageRefused(f"{where}: format_version {version!r} is not a version number")
    if version > FORMAT_VERSION:
        raise PackageRefused(f"{where} was written by a newer VisiBake (scene package format {version}; this "
                             f"VisiBake reads format {FORMAT_VERSION}): update VisiBake on this machine")
    if version != FORMAT_VERSION:
        raise PackageRefused(f"{where}: scene package format {version} is not one this VisiBake reads "
                             f"(it reads format {FORMAT_VERSION})")
    theirs, ours = manifest.get("visibake_version"), visibake_version()
    if theirs != ours:
        raise PackageRefused(f"{where} was written by VisiBake {theirs}, and this is VisiBake {ours}: a worker must "
                             "run the same VisiBake as the machine that wrote its packages")
    missing = sorted(_MANIFEST_KEYS - manifest.keys())
    unexpected = sorted(manifest.keys() - _MANIFEST_KEYS)
    if missing or unexpected:
        raise PackageRefused(f"{where} is damaged: its manifest lacks {missing} and has unexpected {unexpected}")
    try:
        checksum = manifest_checksum(manifest)
    except ValueError:
        checksum = None
    if checksum is None or checksum != manifest["checksum"]:
        raise PackageRefused(f"{where} is damaged or was changed: its manifest does not match its checksum "
                             f"(recorded {manifest['checksum']!r}, computed {checksum!r})")
    # The checksum vouches for the content; what follows guards against a writer that broke the format.
    tree, entries, created = manifest["tree"], manifest["arrays"], manifest["created"]
    if type(tree) is not dict or tree.keys() != _TREE_KEYS:
        raise PackageRefused(f"{where} is damaged: its tree must hold exactly {sorted(_TREE_KEYS)}")
    if type(entries) is not list or not all(_is_array_entry(entry) for entry in entries):
        raise PackageRefused(f"{where} is damaged: its arrays list is malformed")
    if type(created) is not str:
        raise PackageRefused(f"{where} is damaged: its created time is not a string")
    return manifest


def _is_array_entry(entry) -> bool:
    return (type(entry) is dict and entry.keys() == {"dtype", "shape", "blake2b"}
            and type(entry["dtype"]) is str and type(entry["blake2b"]) is str
            and type(entry["shape"]) is list and all(type(n) is int and n >= 0 for n in entry["shape"]))


def _read_arrays(archive: zipfile.ZipFile, entries: list[dict], where: str) -> list[np.ndarray]:
    names = archive.namelist()
    expected = {MANIFEST_NAME} | {f"arrays/{index}.npy" for index in range(len(entries))}
    if len(names) != len(set(names)) or set(names) != expected:
        missing, unexpected = sorted(expected - set(names)), sorted(set(names) - expected)
        raise PackageRefused(f"{where} is damaged or was changed: its entries do not match its manifest "
                             f"(missing {missing}, unexpected {unexpected}, or one name twice)")
    return [_read_array(archive, index, entry, where) for index, entry in enumerate(entries)]


def _read_array(archive: zipfile.ZipFile, index: int, entry: dict, where: str) -> np.ndarray:
    """arrays/<index>.npy, its digest checked before numpy parses it, then its dtype and shape."""
    name = f"arrays/{index}.npy"
    digest = hashlib.blake2b(digest_size=_DIGEST_BYTES)
    try:
        with archive.open(name) as stream:
            while chunk := stream.read(_READ_CHUNK):
                digest.update(chunk)
        if digest.hexdigest() != entry["blake2b"]:
            raise PackageRefused(f"{where} is damaged or was changed: {name} does not match its blake2b digest")
        with archive.open(name) as stream:
            array = np.load(stream, allow_pickle=False)
    except DAMAGED_ARCHIVE_ERRORS as error:
        # The archive's own CRC-32 check, a truncated file, a damaged header or stream.
        raise PackageRefused(f"{where} is damaged: {name} cannot be read ({error})") from None
    except ValueError as error:
        raise PackageRefused(f"{where} is damaged: {name} is not an array numpy reads without pickle ({error})") \
            from None
    if type(array) is not np.ndarray or array.dtype.str != entry["dtype"] or list(array.shape) != entry["shape"]:
        found = f"{array.dtype.str} {list(array.shape)}" if isinstance(array, np.ndarray) else type(array).__name__
        raise PackageRefused(f"{where} is damaged: {name} holds {found}, its manifest says "
                             f"{entry['dtype']} {entry['shape']}")
    return array


class _Decoder:
    """JSON nodes -> values, building only the classes of CLASSES."""

    def __init__(self, arrays: list[np.ndarray], where: str):
        self._arrays = arrays
        self._where = where

    def _refuse(self, path: str, reason: str):
        raise PackageRefused(f"{self._where}: {path}: {reason}")

    def decode(self, node, path: str):
        if node is None or type(node) in (bool, int, float, str):
            return node
        kind = node.get("type") if type(node) is dict else None
        if kind not in _NODE_KEYS or node.keys() != _NODE_KEYS[kind]:
            self._refuse(path, f"not a value of a scene package: {json.dumps(node)[:80]}")
        if kind == "float":
            if node["value"] not in _NON_FINITE:
                self._refuse(path, f"unknown float {node['value']!r}")
            return _NON_FINITE[node["value"]]
        if kind == "numpy":
            return self._scalar(node, path)
        if kind == "array":
            index = node["index"]
            if type(index) is not int or not 0 <= index < len(self._arrays):
                self._refuse(path, f"no array {index!r} in the package")
            return self._arrays[index]
        items = node.get("items")
        if kind in ("list", "tuple"):
            if type(items) is not list:
                self._refuse(path, f"a {kind} without items")
            decoded = [self.decode(item, f"{path}[{i}]") for i, item in enumerate(items)]
            return decoded if kind == "list" else tuple(decoded)
        if kind == "dict":
            return self._dict(items, path)
        return self._dataclass(node, path)

    def _scalar(self, node: dict, path: str):
        try:
            dtype = np.dtype(node["dtype"])
            data = bytes.fromhex(node["hex"])
        except (TypeError, ValueError):
            self._refuse(path, f"not a numpy scalar: {node['dtype']!r} {node['hex']!r}")
        if dtype.kind not in ARRAY_KINDS or dtype.fields is not None or dtype.subdtype is not None \
                or len(data) != dtype.itemsize:
            self._refuse(path, f"not a numpy scalar a package holds: dtype {node['dtype']!r}, {len(data)} bytes")
        return np.frombuffer(data, dtype)[0]

    def _dict(self, items, path: str) -> dict:
        result = {}
        if type(items) is not list:
            self._refuse(path, "a dict without items")
        for pair in items:
            if type(pair) is not list or len(pair) != 2 or type(pair[0]) is not str or pair[0] in result:
                self._refuse(path, f"a dict item is not a [str key, value] pair with a new key: "
                                   f"{json.dumps(pair)[:80]}")
            result[pair[0]] = self.decode(pair[1], f"{path}[{pair[0]!r}]")
        return result

    def _dataclass(self, node: dict, path: str):
        name, values = node["class"], node["fields"]
        cls = CLASSES.get(name) if type(name) is str else None
        if cls is None:
            self._refuse(path, f"unknown class {name!r}: a scene package builds only {', '.join(CLASSES)}")
        if type(values) is not dict:
            self._refuse(path, f"a {name} without fields")
        expected = {f.name for f in fields(cls) if f.init}
        if values.keys() != expected:
            self._refuse(path, f"a {name} must have the fields {sorted(expected)}; missing "
                               f"{sorted(expected - values.keys())}, unknown {sorted(values.keys() - expected)}")
        return cls(**{field: self.decode(value, f"{path}.{field}") for field, value in values.items()})
