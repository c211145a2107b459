"""olsplat: open-vocabulary 3D scene understanding for UAVs on a CPU.

The numeric core (``scene``, ``raster``, ``regions``, ``encoders``, ``structure``,
``aggregate``, ``method``, ``query``) is pure functions and dataclasses, and ``storage`` is the
run's on-disk state; none of them touches a socket (docs/architecture.md, "Layers"). Around
them: ``nodes`` (thin wrappers over the core),
``transport`` (ZeroMQ), ``launcher``, ``sources`` and ``telemetry`` (the drone's runtime path);
``pipeline``, ``evaluate``, ``bench`` and ``tools`` (offline runs, studies and the ``olsplat``
command).
"""

__version__ = "0.1.0"
__all__ = ["__version__"]
