"""Launch files and the supervisor that runs them.

``load_launch`` reads and validates a YAML launch file (with ``--set`` overrides) into a
``LaunchConfig``; ``Supervisor(config).run()`` starts its nodes (one process each, or threads of
this process when ``compose: true``), restarts them by policy and returns an exit code. The file
format and the rules (placeholders, remaps, restart policies) are in ``launch/README.md``. The
launch files that ship with olsplat (``files/``) are launched by name: ``load_launch("replay")``.
"""

from ._config import (
    RESTART_POLICIES,
    LaunchConfig,
    LaunchFileError,
    NodeConfig,
    apply_overrides,
    find_launch_file,
    load_launch,
    parse_launch,
    shipped_launch_files,
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
    "find_launch_file",
    "load_launch",
    "parse_launch",
    "resolve_launch",
    "resolve_params",
    "shipped_launch_files",
]
