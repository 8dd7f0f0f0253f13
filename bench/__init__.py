"""Benchmarks and evaluation harnesses (run from the checkout: `python -m bench.NAME [--quick]`).

Each `bench/<name>.py` with a `run()` and `to_markdown()` is also a section of `touchroller report`.
"""
