"""The tiny flight's run folder (``tiny_run``: one view, map version 1), shared with the node tests:
``test_service.py`` reads it as the query server does, without the sockets."""

from tests.nodes.conftest import region_features, tiny_camera, tiny_run  # noqa: F401  (fixtures, by name)
