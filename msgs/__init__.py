"""olsplat_msgs: the wire schema of the node graph (the single source; see the design card).

The message definitions arrive with the node-graph issue; this package exists now so that the
import name and the layout are fixed from the start.
"""

__all__: list[str] = []
