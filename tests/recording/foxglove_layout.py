"""The Foxglove layout shipped as docs/foxglove-layout.json, built with Foxglove's own types.

    python tests/recording/foxglove_layout.py > docs/foxglove-layout.json

needs the ``foxglove`` extra (``foxglove.layouts``); test_foxglove_layout.py
checks that the shipped file is what this builds and that every topic it
shows is one the recorder writes.
"""

from __future__ import annotations

import json


def build() -> dict:
    import foxglove.layouts as fl

    def image(topic: str, title: str) -> fl.ImagePanel:
        return fl.ImagePanel(
            title=title, config=fl.ImageConfig(image_mode=fl.ImageModeConfig(image_topic=topic))
        )

    def scene(title: str, frame: str, topics: list[str], distance: float) -> fl.ThreeDeePanel:
        return fl.ThreeDeePanel(
            title=title,
            config=fl.ThreeDeeConfig(
                follow_tf=frame,
                topics={t: fl.BaseRendererSceneUpdateTopicSettings(visible=True) for t in topics},
                camera_state=fl.ThreeDeeCameraState(distance=distance, perspective=True),
            ),
        )

    def plot(title: str, paths: list[str]) -> fl.PlotPanel:
        return fl.PlotPanel(
            title=title, config=fl.PlotConfig(paths=[fl.PlotSeries(value=p) for p in paths])
        )

    def split(direction: str, *items: tuple[float, object]) -> fl.SplitContainer:
        return fl.SplitContainer(
            direction=direction,
            items=[fl.SplitItem(proportion=p, content=c) for p, c in items],
        )

    pads = split(
        "column",
        (1, image("robot/pads/finger_1", "Pad, finger 1")),
        (1, image("robot/pads/finger_2", "Pad, finger 2")),
    )
    top = split(
        "row",
        (2, image("camera/image", "Camera")),
        (1, pads),
        (2, scene("Palm", "palm", ["operator/palm", "robot/palm"], 0.15)),
        (2, scene("Arm", "base", [], 1.2)),  # its transforms show as frames
    )
    link = split(
        "row",
        (
            2,
            plot(
                "Link",
                [
                    "operator/link.link_jitter_ms",
                    "operator/link.link_loss_rate",
                    "robot/link.arm_speed_m_s",
                ],
            ),
        ),
        (
            1,
            fl.StateTransitionsPanel(
                title="Link state",
                config=fl.StateTransitionsConfig(
                    paths=[
                        fl.StateTransitionsSeries(value="operator/link.state"),
                        fl.StateTransitionsSeries(value="robot/link.state"),
                    ]
                ),
            ),
        ),
        (1, fl.LogPanel(title="Log", config=fl.LogConfig(topic_to_render="log"))),
    )
    layout = fl.Layout(content=split("column", (3, top), (2, link)))
    return json.loads(layout.to_json())


if __name__ == "__main__":
    print(json.dumps(build(), indent=2))
