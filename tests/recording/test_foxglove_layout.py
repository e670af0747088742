"""The Foxglove layout shipped with the docs opens onto what a recording holds."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from common.recording import foxglove
from common.recording.channels import CHANNELS

REPO = Path(__file__).resolve().parents[2]
LAYOUT = REPO / "docs" / "foxglove-layout.json"
OLD = Path(__file__).parent / "fixtures" / "session-v1"


def _panels(node: dict):
    if node.get("type") == "panel":
        yield node
    for item in node.get("items", []):
        yield from _panels(item["content"])


def _split_path(path: str) -> tuple[str, str]:
    """``operator/link.link_jitter_ms`` -> (topic, field)."""
    topic, _, field = path.partition(".")
    return topic, field


def test_the_layout_shows_topics_a_recording_has():
    layout = json.loads(LAYOUT.read_text())
    assert layout["version"] == 1
    written = (
        set(CHANNELS) | set(foxglove.VIEW_TOPICS) | set(foxglove.IN_PLACE) | {foxglove.LOG_CHANNEL}
    )
    kinds: dict[str, list] = {}
    fields: list[tuple[str, str]] = []
    for panel in _panels(layout["content"]):
        config = panel["config"]
        kinds.setdefault(panel["panelType"], []).append(panel["title"])
        if panel["panelType"] == "Image":
            topic = config["imageMode"]["imageTopic"]
            assert topic in written
            assert (foxglove.VIEW_TOPICS | foxglove.IN_PLACE)[topic].endswith("Image")
        elif panel["panelType"] == "ThreeDee":
            for topic in config.get("topics", {}):
                assert foxglove.VIEW_TOPICS[topic] == "foxglove.SceneUpdate"
            assert config["followTf"] in {foxglove.BASE_FRAME, foxglove.PALM_FRAME}
        elif panel["panelType"] in ("Plot", "StateTransitions"):
            fields += [_split_path(p["value"]) for p in config["paths"]]
        elif panel["panelType"] == "Log":
            assert config["topicToRender"] == foxglove.LOG_CHANNEL
    assert len(kinds["Image"]) == 3 and len(kinds["ThreeDee"]) == 2, kinds
    assert "Plot" in kinds and "Log" in kinds
    # every plotted field is in the recorded records (an old session's: the fields are the same)
    from common.recording.mcap_recorder import read_recording

    first: dict[str, dict] = {}
    for name in ("robot", "operator"):
        for channel, _, record in read_recording(OLD / f"{name}.mcap"):
            first.setdefault(channel, record)
    for topic, field in fields:
        assert field in first[topic], f"{topic}.{field}"


def test_the_layout_is_foxgloves_own_form():
    """The shipped file is what Foxglove's layout types build (foxglove_layout.py here)."""
    pytest.importorskip("foxglove.layouts", reason="Foxglove's layout types: the 'foxglove' extra")
    from foxglove_layout import build

    assert json.loads(LAYOUT.read_text()) == build()
