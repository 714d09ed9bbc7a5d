"""Single-question diagnostics, each run as ``python -m benchmarks.diagnostics.<name>`` from the repository root."""
