"""The exceptions that cross module boundaries, and what each means to the user.

A :class:`BakeRefused` (or a subclass) is the user's error: the message says what
to change, and the command line exits with status 2. :class:`Cancelled` stops a bake
on request. Anything else escaping a bake is a bug (exit status 1).
"""
from __future__ import annotations


class Cancelled(Exception):
    """Raised by a progress callback to stop a bake; nothing has been written."""


class BakeRefused(ValueError):
    """The bake cannot run with these inputs; the message says why and what to change."""


class LayoutError(BakeRefused):
    """An object cannot get a bake layout (UV map, atlas size); the message says why."""


class UnwrapFailed(LayoutError):
    """xatlas could not unwrap the object, or refused its mesh (mode auto then falls back
    to vertex tables)."""


class OutputRefused(BakeRefused):
    """A result cannot be written without harm: a name VisiBake does not own, or values
    no output may hold."""


class DeviceError(BakeRefused):
    """The requested device cannot run this bake; the message says why and what to use."""


class SetupError(BakeRefused):
    """A lighting setup file or sun sweep that cannot be used; the message names the place."""


class VolumeRefused(BakeRefused):
    """A volume cannot be lit as given (an empty or unusable grid, a grid too large); the
    message names the volume and what to change."""


class AppearanceRefused(BakeRefused):
    """A micro-geometry tile or a BRDF/BTF request that cannot be simulated as given."""
