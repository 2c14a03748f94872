"""Shared fixtures: fail any test in which canopen logged an ERROR (it swallows exceptions raised in
subscribe callbacks and only logs them)."""

from __future__ import annotations

import logging
import signal
import sys
from pathlib import Path

import pytest

# A suite started in the background by a non-interactive shell (`cmd &` in a script, CI runners) inherits
# SIGINT ignored (POSIX), and so does every program the tests start: `drivectl shell` and `drivectl ui` then
# never see the tests' Ctrl-C, and their tests wait out their timeouts. Caught, not ignored, here: the
# programs the tests start get the default disposition and install their own handlers.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)

sys.path.insert(0, str(Path(__file__).resolve().parent))  # tests/helpers.py


class _CanopenErrors(logging.Handler):
    def __init__(self) -> None:
        super().__init__(level=logging.ERROR)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


@pytest.fixture(autouse=True)
def fail_on_canopen_errors():
    handler = _CanopenErrors()
    logger = logging.getLogger("canopen")
    logger.addHandler(handler)
    try:
        yield handler
    finally:
        logger.removeHandler(handler)
    if handler.records:
        msgs = "; ".join(f"{r.name}: {r.getMessage()}" for r in handler.records)
        pytest.fail(f"canopen logged ERROR (an exception in a callback was swallowed): {msgs}")
