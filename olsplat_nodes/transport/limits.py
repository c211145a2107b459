"""Receive size limits of the graph's sockets, sized to the largest legitimate message each one
carries (a bigger frame is refused by libzmq from its size header, counted, and the connection
made again): a hostile or broken peer cannot make a node allocate more than this per message.

Data sockets (frames, region features) take their limit from the node's ``max_message_mb``
parameter, since it depends on the camera; the control sockets use these.
"""

# acknowledgements, map announcements, EndOfStream (its list of frame names: ~100,000 names
# of 30 bytes), heartbeats
CONTROL_MAX_BYTES = 8 * 2**20
# a ground station's request: a query text and at most a few dozen negatives of 200 characters
REQUEST_MAX_BYTES = 1 * 2**20
