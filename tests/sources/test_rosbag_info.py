"""``olsplat bag info`` on bags written here: what it prints, and exit 1 with one line on a bad bag."""

from __future__ import annotations

import pytest

from olsplat_nodes.cli import main
from olsplat_nodes.sources.rosbag_info import bag_summary

from .bags import compressed, contract_messages, odometry, rigid, write_bag


def test_info_lists_topics_roles_the_tf_tree_and_what_it_reads(tmp_path, capsys):
    messages, custom, _ = contract_messages(count=3)
    bag = write_bag(tmp_path / "flight_bag", [*messages, ("/odom", messages[1][1], odometry(messages[1][1], rigid()))],
                    custom=custom, storage="sqlite3")  # fmt: skip
    assert main(["bag", "info", str(bag), "--check"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0] == f"bag: {bag} (storage sqlite3, ros_distro rosbags)"
    rows = {line.split()[0]: line.split()[1:4] for line in out if line.startswith("  /")}
    assert rows == {
        "/camera/camera_info": ["sensor_msgs/msg/CameraInfo", "3", "camera_info"],
        "/camera/image/compressed": ["sensor_msgs/msg/CompressedImage", "3", "image"],
        "/odom": ["nav_msgs/msg/Odometry", "1", "odometry"],
        "/tf": ["tf2_msgs/msg/TFMessage", "3", "tf"],
        "/tf_static": ["tf2_msgs/msg/TFMessage", "1", "tf_static"],
    }
    assert "plumb_bob 80x60, frame camera_optical_frame" in next(line for line in out if "/camera/camera_info" in line)
    tree = out.index("tf tree (/tf_static and the first 3 /tf messages):")
    assert out[tree + 1 : tree + 4] == [
        "  map",
        "    camera_link (dynamic, 3 stamps)",
        "      camera_optical_frame (static)",
    ]
    assert "frame names: 3" in out
    assert (
        "reads: images /camera/image/compressed, intrinsics /camera/camera_info, pose tf map -> camera_optical_frame"
        in out
    )
    assert f"record: olsplat record --source-kind replay --source {bag} --out flight.mcap" in out
    assert out[-1] == "check: 3 frames read"


@pytest.mark.parametrize(
    ("change", "params", "problem"),
    [
        ("none", ["--set", "bag_world_frame=odom"], "/camera/image/compressed: no tf frame 'odom'; known frames:"),
        ("no_info", [], "no camera_info topic (topics: /camera/image/compressed, /tf, /tf_static)"),
        ("late", ["--check"], "/camera/image/compressed: none of the 3 frames has a pose within bag_tolerance_s=0.1"),
        ("txt", [], "not a ROS 2 bag: expected a rosbag2 folder (metadata.yaml), a .mcap or a .db3"),
        ("cut", [], "cannot open the bag (AnyReaderError: File end magic is invalid.)"),
    ],
)
def test_info_exits_1_with_one_line(tmp_path, capsys, change, params, problem):
    messages, custom, _ = contract_messages(count=3)
    if change == "no_info":
        messages = [m for m in messages if m[0] != "/camera/camera_info"]
    if change == "late":
        late = [
            (t, s + 10**10, compressed(s + 10**10, bytes(m.data))) for t, s, m in messages if t.endswith("compressed")
        ]
        messages = [m for m in messages if not m[0].endswith("compressed")] + late
    bag = write_bag(tmp_path / "b", messages, custom=custom)
    if change == "txt":
        bag = tmp_path / "notes.txt"
        bag.write_text("not a bag")
    if change == "cut":
        bag = bag / "b.mcap"
        bag.write_bytes(bag.read_bytes()[:300])
    assert main(["bag", "info", str(bag), *params]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"olsplat bag: error: {bag}: {problem}"), err


def test_summary_of_a_bag_without_tf_names_its_pose_topic(tmp_path):
    messages = contract_messages(count=2)[0]
    messages = [m for m in messages if not m[0].startswith("/tf")] + [
        ("/odom", messages[1][1], odometry(messages[1][1], rigid()))
    ]
    summary = bag_summary(write_bag(tmp_path / "b", messages))
    assert summary.selection is not None and summary.selection.pose == "/odom" and summary.problem == ""
    assert summary.tf_tree == [] and summary.frame_names == 0
