"""A simulated flight written as a ROS 2 bag runs through the launched graph with the bag as the
ingest's source (``ingest.source=BAG``, nothing else named) and gives the map of its MCAP
replay log: the final map equals ``olsplat aggregate``'s over the same scene to the bit, as the
replay log's does (``test_graph.test_the_streamed_map_equals_the_offline_map``)."""

from __future__ import annotations

import numpy as np
import pytest

from olsplat_nodes.launcher import Supervisor
from olsplat_nodes.sources.replay_log import read_replay
from olsplat_nodes.sources.rosbag_write import write_rosbag2
from olsplat_nodes.storage import LanguageMap, ObservationStore, latest_map
from tests.helpers import free_port

from .conftest import launch_tiny


@pytest.mark.timeout(600)
@pytest.mark.parametrize(("storage", "inner"), [("mcap", False), ("sqlite3", True)])
def test_a_bag_of_the_simulated_flight_gives_the_map_of_its_replay_log(storage, inner, tiny, tmp_path, offline_map):
    scene, summary = tiny
    bag = tmp_path / "flight_bag"
    assert write_rosbag2(bag, read_replay(scene / "replay.mcap"), storage=storage) == summary["views"]
    source = bag / f"flight_bag.{'db3' if storage == 'sqlite3' else 'mcap'}" if inner else bag
    run_dir = tmp_path / "run"
    overrides = (f"ingest.source={source}", "launch.compose=true")
    assert Supervisor(launch_tiny(scene, run_dir, free_port(), *overrides)).run() == 0
    names = ObservationStore(run_dir / "store", 1).names()
    assert sorted(names) == sorted(frame.name for frame in read_replay(scene / "replay.mcap"))
    record = latest_map(run_dir / "map")
    assert record["final"] and record["views"] == summary["views"]
    streamed = LanguageMap.load(record["path"])
    assert np.array_equal(streamed.observed, offline_map.observed) and streamed.observed.sum() > 1000
    np.testing.assert_array_equal(streamed.features, offline_map.features)
