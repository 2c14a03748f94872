"""The ``health`` extra's libraries, imported when a health command needs them, so that the core package
stays light and a missing one is said in one line."""

from __future__ import annotations

from importlib import import_module
from types import ModuleType

from drivectl.errors import InputError

EXTRA = "pip install 'drivectl[health]'"


class MissingExtra(InputError):
    """A library of the ``health`` extra is not installed (exit 2, before anything is written)."""


def need(module: str) -> ModuleType:
    """``import module``, or one line naming it and the extra that brings it."""
    try:
        return import_module(module)
    except ImportError:
        top = module.partition(".")[0]
        raise MissingExtra(f"health: needs {top}, which is not installed ({EXTRA})") from None
