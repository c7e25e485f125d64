"""Benchmarks: ``python -m bench`` discovers every ``bench/*_bench.py`` module and prints
its table (see bench/README.md for the module contract)."""
