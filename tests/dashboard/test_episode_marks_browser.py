"""Marking episodes on the dashboard: a real page, a real operator node recording to MCAP.

The page is driven as a person drives it (a typed task, a click, a key);
the marks are checked where the export reads them, in the operator's
recording, and on the robot's side of the link, where none may arrive.
"""

from __future__ import annotations

import json
import time

import pytest
from headless_chromium import Chromium, needs_chromium
from test_dashboard_browser import operator_station
from websockets.sync.client import connect

from common.recording.episode_marks import CHANNEL
from common.recording.mcap_recorder import McapRecorder, read_recording
from operator_side.dashboard import Dashboard, DashboardConfig
from operator_side.node import OperatorNode
from operator_side.node.config import OperatorConfig
from operator_side.servos.in_memory import InMemoryServoBus

pytestmark = [pytest.mark.timeout(60)]

KEY_DELETE = {"key": "Delete", "code": "Delete", "windowsVirtualKeyCode": 46}
MARK_ACKS = "dxp.marks.length"


@pytest.fixture
def recording_station(zmq_ctx, tmp_path):
    """Stand-in robot, operator node recording to operator.mcap, dashboard; torn down in order."""
    recorder = McapRecorder(tmp_path / "operator.mcap", fsync=False)
    try:
        with operator_station(zmq_ctx, recorder) as (robot, _node, dashboard):
            yield robot, recorder, dashboard
    finally:
        recorder.close()


@pytest.mark.slow
@needs_chromium
def test_marks_made_on_the_page_are_recorded_and_never_reach_the_robot(recording_station):
    robot, recorder, dashboard = recording_station
    robot.pattern = 6
    with Chromium(width=1280, height=900) as page:
        page.navigate(dashboard.url)
        page.wait_for("dxp.hello !== null && dxp.jog !== null", 10)
        # a task typed into the field, then the Failed button
        page.click("#mark-task")
        page.call("Input.insertText", text="pipette slipped")
        page.click("#mark-failed")
        page.wait_for(f"{MARK_ACKS} >= 1", 5)
        assert "episode marked failed (task: pipette slipped)" in page.evaluate(
            "document.getElementById('mark-status').textContent"
        )
        # the field emptied, the focus off it, the Delete key: a discard with no task
        page.evaluate(
            "(() => { const t = document.getElementById('mark-task'); t.value = '';"
            " t.blur(); return true; })()"
        )
        for kind in ("keyDown", "keyUp"):
            page.call("Input.dispatchKeyEvent", type=kind, **KEY_DELETE)
        page.wait_for(f"{MARK_ACKS} >= 2", 5)
        acks = page.evaluate("dxp.marks")
        assert page.page_errors() == []
    assert [(a["ok"], a["kind"], a.get("task")) for a in acks] == [
        (True, "failed", "pipette slipped"),
        (True, "discard", None),
    ]
    assert dashboard.commands.episode_marks == 2
    recorder.close()
    marks = [(t, r) for ch, t, r in read_recording(recorder.path) if ch == CHANNEL]
    assert [(r["kind"], r.get("task"), r["source"]) for _, r in marks] == [
        ("failed", "pipette slipped", "dashboard"),
        ("discard", None, "dashboard"),
    ]
    assert marks[0][0] < marks[1][0]
    time.sleep(0.2)  # anything sent would have reached the stand-in robot by now
    assert robot.commands == []  # a mark is the recording's business only


def test_a_node_that_does_not_record_refuses_marks_and_says_why(zmq_ctx):
    """Through the page's WebSocket with its token, as a script would: nothing is lost quietly."""
    node = OperatorNode(OperatorConfig(), InMemoryServoBus(), ctx=zmq_ctx)
    with (
        Dashboard(node, DashboardConfig(enabled=True, port=0)) as dashboard,
        connect(dashboard.ws_url) as ws,
    ):

        def ask(**fields):
            ws.send(json.dumps({"type": "command", "action": "episode_mark", **fields}))
            while True:
                msg = json.loads(ws.recv(timeout=5))
                if msg["type"] == "ack":
                    return msg

        refused = ask(kind="failed")
        assert not refused["ok"] and "not recording" in refused["error"]
        assert "--record" in refused["error"]
        assert "kind must be one of" in ask(kind="lost")["error"]
        assert "printable" in ask(kind="failed", task="two\nlines")["error"]
        assert "at most 200" in ask(kind="failed", task="x" * 201)["error"]
        assert dashboard.commands.episode_marks == 0
