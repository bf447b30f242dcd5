"""Where a bake will write, checked before any work: the one rule of the command and the operator.

A bake that traces for minutes and then finds its output folder is a file, or its
``--save`` folder read-only, loses all that work; so every destination is checked
first (:func:`destination_problem`, :func:`check_destinations`). The check never
creates a folder: it probes the nearest folder that exists (a temporary file, made
and removed at once), because ``os.access`` says yes to root on a read-only mount
and to anyone on a folder whose ACL says no.
"""
from __future__ import annotations

import os
import tempfile

from ..errors import OutputRefused

FOLDER, FILE = "folder", "file"


def _nearest_existing(path: str) -> str:
    """``path`` or its nearest ancestor that exists (possibly as a file)."""
    current = path
    while not os.path.lexists(current):
        parent = os.path.dirname(current)
        if parent == current:
            break
        current = parent
    return current


def _can_create_in(folder: str) -> str | None:
    """Why no file can be created in the existing ``folder``; None if one can."""
    if not os.access(folder, os.W_OK | os.X_OK):
        return "is not writable"
    try:
        handle, probe = tempfile.mkstemp(prefix=".visibake-probe-", dir=folder)
    except OSError as error:
        return f"is not writable ({error.strerror or error})"
    os.close(handle)
    os.remove(probe)
    return None


def destination_problem(path: str, kind: str, label: str) -> str | None:
    """Why the bake could not write ``path``; None if it can. Changes nothing on disk.

    Parameters
    ----------
    path : the destination (made absolute here)
    kind : ``FOLDER`` (the bake creates it if missing and writes into it) or ``FILE``
        (the bake writes this file, replacing it if it exists)
    label : what the message calls it (an option such as ``--out``)
    """
    path = os.path.abspath(path)
    if kind not in (FOLDER, FILE):
        raise ValueError(f"kind must be {FOLDER!r} or {FILE!r}, got {kind!r}")
    if os.path.isdir(path):
        if kind == FILE:
            return f"{label} {path} is a folder; give a file name"
        reason = _can_create_in(path)
        return None if reason is None else f"{label} {path} {reason}"
    if os.path.lexists(path):
        if kind == FOLDER:
            return f"{label} {path} is a file, not a folder"
        if not os.path.isfile(path):
            # A device, pipe or socket: the file would be replaced, not written into.
            return f"{label} {path} is not a regular file"
        if not os.access(path, os.W_OK):
            return f"{label} {path} is not writable"
        # Blender saves and VisiBake writes reports by replacing the file: its folder must take a new one.
        reason = _can_create_in(os.path.dirname(path))
        return None if reason is None else f"{label} {path}: its folder {reason}"
    existing = _nearest_existing(os.path.dirname(path))
    if not os.path.isdir(existing):
        return f"{label} {path}: {existing} is a file, not a folder"
    reason = _can_create_in(existing)
    return None if reason is None else f"{label} {path}: {existing} {reason}"


def check_destinations(destinations) -> None:
    """Raise :class:`OutputRefused` for the first of ``destinations`` that cannot be written.

    destinations : iterable of (path or None, kind, label); None entries are skipped
    """
    for path, kind, label in destinations:
        if not path:
            continue
        reason = destination_problem(path, kind, label)
        if reason is not None:
            raise OutputRefused(reason)
