"""User names (objects, passes, light groups, setups) as file names and datablock names.

Every name that becomes part of a path goes through :func:`path_component`, every set of
names that shares one folder through :func:`unique_components`, and every path is checked
by :func:`inside_folder` before anything is written there.

Choices, and why:

- Non-ASCII names stay Unicode, NFC-normalised: transliteration would make distinct names
  (Cyrillic, CJK) collide and read worse; every current file system stores UTF-8. macOS
  stores names decomposed (NFD), so two names that differ only in normalisation are one file
  there; both normalise to the same NFC form, and the form that had to change gets a hash.
- A name that had to change in any way keeps a short hash of the *original* name, so
  ``a/b``, ``a_b`` and ``a:b`` never meet, and the file of a name does not depend on which
  other names are baked with it. Only names that are left unchanged and still collide
  (``Box`` and ``box`` on a case-insensitive disk) depend on their neighbours: both get a hash.
- Collisions are compared after NFC and case folding: Windows and macOS disks ignore case.
- Components are capped at :data:`MAX_COMPONENT_BYTES` UTF-8 bytes (most file systems allow
  255, and a long name also lengthens every path below it).
"""
from __future__ import annotations

import hashlib
import os
import re
import unicodedata

from ..errors import OutputRefused
from ..settings import PASSES

MAX_COMPONENT_BYTES = 100
HASH_LENGTH = 8  # hex digits of the name hash: 32 bits, more only if two hashes ever meet

# Invalid in Windows file names, or path syntax anywhere; control characters, DEL and
# lone surrogates (which cannot be encoded as UTF-8) too.
_INVALID = re.compile(r'[<>:"/\\|?*\x00-\x1f\x7f\ud800-\udfff]')
# Windows device names, reserved with any extension too (``con.txt``); ``¹²³`` count as digits there.
_RESERVED = frozenset({"CON", "PRN", "AUX", "NUL", "CONIN$", "CONOUT$"}
                      | {f"{base}{digit}" for base in ("COM", "LPT") for digit in "0123456789¹²³"})


def name_hash(name: str, length: int = HASH_LENGTH) -> str:
    """A short stable hex hash of ``name`` exactly as given (not normalised)."""
    return hashlib.sha1(name.encode("utf-8", "surrogatepass")).hexdigest()[:length]


def fit_bytes(text: str, max_bytes: int) -> str:
    """``text`` cut to at most ``max_bytes`` UTF-8 bytes, at a character boundary."""
    encoded = text.encode("utf-8", "surrogatepass")
    if len(encoded) <= max_bytes:
        return text
    return encoded[:max_bytes].decode("utf-8", "ignore")


def _cleaned(name: str) -> str:
    cleaned = _INVALID.sub("_", unicodedata.normalize("NFC", name))
    # Windows drops trailing dots and spaces; a leading dot hides the file (and ``..`` is the parent).
    cleaned = cleaned.strip(" ").rstrip(". ")
    if cleaned.startswith("."):
        cleaned = "_" + cleaned[1:]
    if not cleaned:
        return "_"
    stem, dot, rest = cleaned.partition(".")
    if stem.rstrip(" ").upper() in _RESERVED:
        cleaned = stem + "_" + dot + rest
    return cleaned


def path_component(name: str, max_bytes: int = MAX_COMPONENT_BYTES, hashed: bool = False,
                   hash_length: int = HASH_LENGTH) -> str:
    """``name`` as one file or folder name that is valid and safe on Windows, macOS and Linux.

    Unchanged if it already is one; otherwise cleaned (separators and characters Windows
    refuses become ``_``, trailing dots and spaces go, reserved device names get a ``_``),
    cut to ``max_bytes`` UTF-8 bytes, and suffixed ``-<hash of the original>``.
    ``hashed``: add the hash even if the name needed no change (to tell colliding names apart).
    """
    cleaned = _cleaned(name)
    if cleaned == name and not hashed and len(name.encode("utf-8", "surrogatepass")) <= max_bytes:
        return name
    suffix = "-" + name_hash(name, hash_length)
    head = fit_bytes(cleaned, max_bytes - len(suffix))
    return head + suffix


def component_key(component: str) -> str:
    """What a case-insensitive, normalising file system compares: NFC after case folding."""
    return unicodedata.normalize("NFC", unicodedata.normalize("NFC", component).casefold())


def unique_components(names, reserved=(), suffix: str = "", max_bytes: int = MAX_COMPONENT_BYTES) -> dict:
    """One distinct path component for every name that shares a folder.

    Parameters
    ----------
    names : the names (duplicates are one name)
    reserved : components already used in that folder by something else (e.g. ``report.json``)
    suffix : what every component gets appended (``.exr``): collisions are compared with it

    Returns {name: component} (without ``suffix``); no two components, nor a reserved one,
    are equal after case folding and normalisation. Independent of the names' order.
    """
    names = sorted(set(names))
    taken = {component_key(r) for r in reserved}
    components = {n: path_component(n, max_bytes) for n in names}
    hashed = set()
    length = HASH_LENGTH
    while True:
        owners: dict = {}
        for name in names:
            owners.setdefault(component_key(components[name] + suffix), []).append(name)
        clashing = {n for key, group in owners.items() if len(group) > 1 or key in taken for n in group}
        if not clashing:
            return components
        if clashing <= hashed:
            # Two hashes met (or a user named an object like a hashed one twice over): longer hashes.
            length += 8
        for name in clashing:
            components[name] = path_component(name, max_bytes, hashed=True, hash_length=length)
        hashed |= clashing
        if length > 40:
            raise RuntimeError(f"bug: no distinct file names for {sorted(clashing)!r}")


def inside_folder(folder: str, *components: str) -> str:
    """``folder/components...``, refused unless it resolves (links followed) inside ``folder``.

    Raises :class:`core.errors.OutputRefused` for a path that would land elsewhere.
    """
    path = os.path.join(folder, *components)
    # normcase: Windows compares paths without case (and realpath may spell a drive either way).
    root, resolved = os.path.normcase(os.path.realpath(folder)), os.path.normcase(os.path.realpath(path))
    try:
        inside = resolved != root and os.path.commonpath([root, resolved]) == root
    except ValueError:  # on another drive (Windows)
        inside = False
    if not inside:
        raise OutputRefused(f"output {path!r} would be written outside the output folder {folder!r}; "
                            "nothing was written there")
    return path


_HASHED_DATABLOCK = re.compile(r"~[0-9a-f]{12}$")


def datablock_name(prefix: str, parts, max_bytes: int, separator: str = "_", hashed: bool = False,
                   suffix: str = "") -> str:
    """A Blender datablock name ``prefix`` + ``parts`` joined + ``suffix``, within ``max_bytes`` UTF-8 bytes.

    Too long a name (or any, with ``hashed``) has its joined parts cut and followed by
    ``~<hash of all parts>``, so the same parts always give the same name and Blender never
    cuts it (cut names would pile up on re-bakes and no longer be found). A plain name never
    looks like a hashed one.
    """
    parts = list(parts)
    joined = separator.join(parts)
    name = prefix + joined + suffix
    if not hashed and len(name.encode("utf-8")) <= max_bytes and not _HASHED_DATABLOCK.search(prefix + joined):
        return name
    tag = "~" + name_hash("\x00".join(parts), 12)
    room = max(max_bytes - len((prefix + tag + suffix).encode("utf-8")), 0)
    # Cut the first part (the object) and keep the rest (the pass) readable, while that leaves a few bytes of it.
    rest = separator.join(parts[1:])
    head_room = room - len((separator + rest).encode("utf-8")) if len(parts) > 1 else room
    if len(parts) > 1 and head_room >= min(len(parts[0].encode("utf-8")), 8):
        joined = fit_bytes(parts[0], head_room) + separator + rest
    else:
        joined = fit_bytes(joined, room)
    return prefix + joined + tag + suffix


def _pass_splits(text: str, passes) -> list[int]:
    """Where ``text`` (``<object>_<pass>``) could be split into an object and a pass name."""
    return [i for i, character in enumerate(text) if character == "_" and i > 0
            and any(text[i + 1:] == p or text[i + 1:].startswith(p + "_") for p in passes)]


def image_name(object_name: str, pass_name: str, max_bytes: int, passes=None) -> str:
    """The name of the image of ``object_name``'s pass ``pass_name``: ``VB_<object>_<pass>``.

    Distinct for distinct (object, pass) pairs: where that form reads two ways (object ``A``'s
    pass ``lighting_direct``, the light group ``direct``, and object ``A_lighting``'s pass
    ``direct``), or is too long for Blender (``max_bytes``), it is cut and hashed instead
    (:func:`datablock_name`). ``passes``: the base pass names (default core.settings.PASSES);
    a pass is one of them or ``<base>_<light group>``.
    """
    passes = PASSES if passes is None else passes
    text = f"{object_name}_{pass_name}"
    unambiguous = _pass_splits(text, passes) == [len(object_name)]
    return datablock_name("VB_", [object_name, pass_name], max_bytes, hashed=not unambiguous)


def renamed_warnings(renamed: list) -> list[str]:
    """The report's warning about outputs not named after their object, pass or setup.

    ``renamed``: [{"name", "kind", "path"}] (Report.renamed_outputs); at most one line.
    """
    if not renamed:
        return []
    shown = "; ".join(f"{r['kind']} {r['name']!r} -> {r['path']}" for r in renamed[:5])
    more = f"; and {len(renamed) - 5} more" if len(renamed) > 5 else ""
    return [f"{len(renamed)} output name(s) changed to safe, distinct file or image names (listed in "
            f"renamed_outputs): {shown}{more}"]
