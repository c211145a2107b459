"""The nodes: the drone's five (ingest, region_encoder, accumulator, refiner, query_server) and
the ground station's monitor, each a thin wrapper over the core: decode a message, call a pure
function, encode the answer. ``base.py`` holds what they share (typed ``Params``, the loop,
sockets, stats), ``transport/convert.py`` every message <-> core conversion (the ground
station's link uses it too); no node imports another.
``NODES`` maps an executable name (as launch files write it) to its class;
``python -m olsplat_nodes.nodes EXEC`` runs one node in its own process."""

NODES = {
    "ingest": "olsplat_nodes.nodes.ingest:IngestNode",
    "region_encoder": "olsplat_nodes.nodes.region_encoder:RegionEncoderNode",
    "accumulator": "olsplat_nodes.nodes.accumulator:AccumulatorNode",
    "refiner": "olsplat_nodes.nodes.refiner:RefinerNode",
    "query_server": "olsplat_nodes.nodes.query_server:QueryServerNode",
    "ground_monitor": "olsplat_nodes.nodes.ground_monitor:GroundMonitorNode",  # the ground station's side
}
