"""Benchmarks: ``python -m bench <name> [--quick] [--json PATH]``. Each prints tables and writes JSON."""
