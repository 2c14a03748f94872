"""The root of drivectl's exceptions, and the exit codes they carry.

Every error a command can end with derives from :class:`DrivectlError`; its class says the exit code
(:attr:`DrivectlError.exit_code`), so the CLI maps an exception to its code in one place
(tools/cli/exits.py) instead of keeping a list per command. The built-in bases stay (``ValueError``
for bad input, ``RuntimeError`` for an axis that cannot do what was asked), so library callers that
catch those keep working.

Exit codes (the CLI's contract, tools/cli/main.py says what each means): 0 done, 1 stopped (a limit,
a refusing bus or drive, data that cannot be fitted), 2 bad input, 3 a fault ended the run, 4 done with
warnings.
"""

from __future__ import annotations

from typing import ClassVar

EXIT_OK, EXIT_STOPPED, EXIT_BAD_INPUT, EXIT_FAULT, EXIT_WARNINGS = 0, 1, 2, 3, 4


class DrivectlError(Exception):
    """Root of drivectl's errors; a command that ends with one exits with its ``exit_code``."""

    exit_code: ClassVar[int] = EXIT_STOPPED


class InputError(DrivectlError, ValueError):
    """Bad input (a file, a key, a flag, a value): one line naming it, before anything moves."""

    exit_code: ClassVar[int] = EXIT_BAD_INPUT
