"""Benchmarks that reproduce the paper's measurements (run them with ``python -m``)."""
