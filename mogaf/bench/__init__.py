"""Benchmarks: `python -m mogaf.bench <name> [options]` prints a table.

Speed and memory targets live here, never in timed tests. Each benchmark is a
module `mogaf.bench.<name>` exposing `main(argv: list[str]) -> int`.
"""
