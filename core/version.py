"""VisiBake's own version, read from the extension's blender_manifest.toml (the one place it is set)."""
from __future__ import annotations

import functools
import tomllib
from pathlib import Path

# The manifest sits at the extension's root, beside core/, in a checkout and in an installed extension alike.
MANIFEST_PATH = Path(__file__).resolve().parents[1] / "blender_manifest.toml"


@functools.cache
def visibake_version() -> str:
    """The ``version`` field of blender_manifest.toml, e.g. '0.1.0'.

    Raises RuntimeError where the manifest is missing or has no version: core/ was copied
    without the extension around it, and nothing can tell which VisiBake it is.
    """
    try:
        with open(MANIFEST_PATH, "rb") as stream:
            manifest = tomllib.load(stream)
    except (OSError, tomllib.TOMLDecodeError) as error:
        raise RuntimeError(f"cannot read VisiBake's version from {MANIFEST_PATH}: {error}") from error
    version = manifest.get("version")
    if not isinstance(version, str) or not version:
        raise RuntimeError(f"{MANIFEST_PATH} has no version field")
    return version
