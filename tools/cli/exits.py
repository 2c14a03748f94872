"""Exceptions to exit codes, in one place: a command ended by a :class:`~drivectl.errors.DrivectlError`
prints its one line and exits with the code its class carries (drivectl/errors.py)."""

from __future__ import annotations

import functools
import sys
from collections.abc import Callable
from typing import TypeVar

from drivectl.errors import DrivectlError

F = TypeVar("F", bound=Callable[..., int])


def report(exc: DrivectlError) -> int:
    """Say ``exc`` in one line on stderr and return its exit code."""
    print(f"drivectl: {exc}", file=sys.stderr)
    return exc.exit_code


def exits_on_error(command: F) -> F:
    """A command function (args -> exit code) whose drivectl errors end it with their own code."""

    @functools.wraps(command)
    def run(*args: object, **kwargs: object) -> int:
        try:
            return command(*args, **kwargs)
        except DrivectlError as exc:
            return report(exc)

    return run  # type: ignore[return-value]
