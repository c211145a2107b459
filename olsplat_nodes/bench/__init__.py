"""Benchmark scripts (``olsplat bench ...``): they print figures; no test times anything."""
