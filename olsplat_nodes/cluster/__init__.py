"""Beyond one machine: the aggregation sharded by ground tile on a Ray cluster (an optional
extra, ``pip install olsplat[cluster]``; nothing outside this package imports Ray)."""
