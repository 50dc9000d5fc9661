"""Benchmarks that print numbers: `python -m pi0_armfix.bench {data|model|train} [flags]`."""
