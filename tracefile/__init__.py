"""The trace contract (docs/trace-format.md): the format, its streaming writer, its metrics and plots.

The lowest of drivectl's own layers beside driver/ and profiles/: the runtime writes traces, the
commands and explain read them, so the format lives where both can import it.
"""
