"""Bus logs in: a CAN log that python-can reads (candump, .asc, .blf, .trc, .csv, .mf4) decoded, turned into a
trace, replayed.

See docs/guide/buslog.md; the trace written is format v1 (docs/trace-format.md).
"""

from drivectl.tools.buslog.convert import LOG_SUFFIXES, BusLogError, is_bus_log, log_to_trace

__all__ = ["LOG_SUFFIXES", "BusLogError", "is_bus_log", "log_to_trace"]
