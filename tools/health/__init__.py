"""Axis health over a machine's life (docs/health.md): the trace store (Parquet samples, a DuckDB
catalog) and its ``drivectl health`` commands. pyarrow and duckdb are the ``health`` extra, imported
only here and only when used (:func:`drivectl.tools.health.deps.need`)."""
