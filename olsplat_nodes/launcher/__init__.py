"""Launch files and the supervisor that runs them.

``load_launch`` reads and validates a YAML launch file (with ``--set`` overrides) into a
``LaunchConfig``; ``Supervisor(config).run()`` starts its nodes (one process each, or threads of
this process when ``compose: true``), restarts them by policy and returns an exit code. The file
format and the rules (placeholders, remaps, restart policies) are in ``launch/README.md``.
"""

from ._config import (
    RESTART_POLICIES,
    LaunchConfig,
    LaunchFileError,
    NodeConfig,
    apply_overrides,
    load_launch,
    parse_launch,
)
from ._resolve import resolve_launch, resolve_params
from ._supervisor import Supervisor

__all__ = [
    "RESTART_POLICIES",
    "LaunchConfig",
    "LaunchFileError",
    "NodeConfig",
    "Supervisor",
    "apply_overrides",
    "load_launch",
    "parse_launch",
    "resolve_launch",
    "resolve_params",
]
