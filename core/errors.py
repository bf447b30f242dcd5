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
