"""Benchmarks of bdpt-drjit against Mitsuba 3 (see benchmarks/README.md and RESULTS.md)."""
