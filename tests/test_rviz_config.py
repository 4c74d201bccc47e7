"""config/patchwalk.rviz loads as RViz 2's YAML and shows what the nodes publish: every topic it
subscribes is one of the nodes' names (or robot_state_publisher's /robot_description), with the QoS
the publisher offers, in the frame the mapper publishes."""

from pathlib import Path

import yaml

from test_readme_names import names_in_code

ROOT = Path(__file__).resolve().parents[1]
SENSOR_TOPICS = {"/camera/depth/image_raw", "/camera/depth/camera_info", "/imu/data"}


def test_rviz_config_displays_the_nodes_topics():
    config = yaml.safe_load((ROOT / "config" / "patchwalk.rviz").read_text())
    manager = config["Visualization Manager"]
    assert manager["Global Options"]["Fixed Frame"] == "odom"
    displays = {d["Class"]: d for d in manager["Displays"]}
    for needed in ["rviz_default_plugins/TF", "rviz_default_plugins/RobotModel", "rviz_default_plugins/MarkerArray",
                   "rviz_default_plugins/PointCloud2", "rviz_default_plugins/Image"]:
        assert needed in displays, needed
    known = names_in_code() | {"/robot_description"}
    for display in manager["Displays"]:
        topic = display.get("Topic") or display.get("Description Topic")
        if topic is None:
            continue
        assert topic["Value"] in known, f"{display['Name']}: {topic['Value']} is not a patchwalk topic"
        expected = "Best Effort" if topic["Value"] in SENSOR_TOPICS else "Reliable"
        assert topic["Reliability Policy"] == expected, display["Name"]
