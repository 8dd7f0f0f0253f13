"""The RViz 2 config and the Foxglove layout that ship in config/ load, and show our topics and frames."""
from __future__ import annotations

import json

import yaml

from touchroller_bringup import names
from touchroller_driver.paths import config_path


def _topics(node) -> set[str]:
    """Every `Topic: {Value: ...}` (RViz) or `imageTopic` / topic key (Foxglove) in a config tree."""
    found: set[str] = set()
    if isinstance(node, dict):
        for key, value in node.items():
            if key == "Topic" and isinstance(value, dict):
                found.add(value["Value"])
            elif key in ("imageTopic", "topicToRender") and isinstance(value, str):
                found.add(value)
            elif key == "topics" and isinstance(value, dict):
                found |= set(value)
            found |= _topics(value)
    elif isinstance(node, list):
        for value in node:
            found |= _topics(value)
    return found


OUR_TOPICS = {names.topic(t, names.DEFAULT_NAMESPACE)
              for t in (names.IMAGE, "contacts", "map", names.MAP_MARKERS, names.FINDINGS)} \
    | {"/diagnostics"}


def test_rviz_config_loads_with_the_robot_base_fixed_and_our_topics():
    config = yaml.safe_load(config_path("rviz", "touchroller.rviz").read_text())
    manager = config["Visualization Manager"]
    assert manager["Global Options"]["Fixed Frame"] == names.BASE_FRAME
    classes = {d["Class"] for d in manager["Displays"]}
    assert {"rviz_default_plugins/TF", "rviz_default_plugins/PointStamped", "rviz_default_plugins/Image",
            "rviz_default_plugins/MarkerArray"} <= classes
    assert _topics(config) <= OUR_TOPICS and len(_topics(config)) == 5
    for latched_topic in ("/map", "/findings"):   # the map and the findings are latched
        latched = next(d for d in manager["Displays"] if d.get("Topic", {}).get("Value", "").endswith(latched_topic))
        assert latched["Topic"]["Durability Policy"] == "Transient Local"
    markers = {d["Topic"]["Value"] for d in manager["Displays"] if d["Class"] == "rviz_default_plugins/MarkerArray"}
    assert markers == {names.topic(names.MAP_MARKERS, names.DEFAULT_NAMESPACE),
                       names.topic(names.FINDINGS, names.DEFAULT_NAMESPACE)}


def test_foxglove_layout_loads_and_every_panel_it_lays_out_is_configured():
    layout = json.loads(config_path("foxglove", "touchroller.json").read_text())

    def leaves(node):
        return [node] if isinstance(node, str) else leaves(node["first"]) + leaves(node["second"])

    assert sorted(leaves(layout["layout"])) == sorted(layout["configById"])
    assert _topics(layout["configById"]) == OUR_TOPICS
    assert layout["configById"]["3D!touchroller"]["followTf"] == names.BASE_FRAME
