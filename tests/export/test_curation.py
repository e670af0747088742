"""Curating a dataset: marks made on the dashboard while recording, then ``deepxpalm export``.

The demo runs with its dashboard and records; a client holding the page's
token marks, through the page's WebSocket, one grasp failed (with a task
string) and the grasp after next discarded, each while the palm shows contact.
The export, given --exclude and --task-file as a user types them, is
loaded by LeRobot's own ``LeRobotDataset``: the discarded grasp and the
excluded one are not there, the failed one is, with ``next.success``
false and its task, and every other episode ends with ``next.success``.
"""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
from tests_support import DashboardDemo
from websockets.sync.client import connect

from common.recording.episode_marks import CHANNEL, read_marks
from common.recording.mcap_recorder import read_recording

pytestmark = [pytest.mark.slow, pytest.mark.untimed]

FPS = 30
FAILED_TASK = "grasp the pipette: it slipped"
FILE_TASK = "grasp the pipette, second try"
#: contact shown this long on the page before marking: the grasp is one the export cuts
#: (its min_grasp_s is 0.2 s)
CONTACT_S = 0.4
#: no contact this long on the page between two contacts: a release, and a new grasp began
#: (the script pauses 0.4 s). A pause is measured when contact comes back: the page pushes on
#: a change and four times a second, so it may send nothing else while the palm is off.
APART_S = 0.25
#: the client marks the first grasp it sees held failed and the one after next discarded,
#: a whole grasp between them. The page and the recording see a release from different
#: processes: beside a loaded machine a starved sensor simulator holds its last contact frame
#: into the pause, and the export (grasp_gap_s 0.3 s) may join two grasps the page saw apart.
#: With a grasp between them, the two marks never fall in one episode.
MARKS = {0: ("failed", FAILED_TASK), 2: ("discard", None)}  # grasps after the first held
#: grasps after the discarded one: its end and two whole grasps (one to exclude, one to retask)
AFTER_DISCARD = 3


class PalmWatch:
    """Contact on the page, in grasps: the grasp it is in and how long it has been held.

    A gap in contact shorter than ``APART_S`` (a stale push on a busy machine) neither ends
    a grasp nor restarts its hold.
    """

    def __init__(self) -> None:
        self.grasp = -1  # grasps begun since watching, -1 until the first contact
        self.touching: bool | None = None
        self.since = 0.0  # when the current run of contact (or of none) began
        self.grasp_since = 0.0  # when the current grasp began
        self.t0 = time.monotonic()
        #: (seconds since watching, grasp, touching): what a failure reports
        self.changes: list[tuple[float, int, bool]] = []

    def see(self, msg: dict) -> bool:
        """Take one page message; whether it was a state with the palm's stimulus."""
        if msg.get("type") != "state" or "stimulus" not in msg:
            return False
        stim = msg["stimulus"]
        contact = stim is not None and max(map(max, stim)) > 0
        now = time.monotonic()
        if contact != self.touching:
            released = self.touching is False and now - self.since >= APART_S
            if contact and (self.grasp < 0 or released):
                self.grasp += 1
                self.grasp_since = now
            self.touching, self.since = contact, now
            self.changes.append((round(now - self.t0, 3), self.grasp, contact))
        return True

    def held_s(self) -> float:
        return time.monotonic() - self.grasp_since if self.touching else 0.0


class MarkingClient:
    """On the page's WebSocket: marks the grasps it sees, as an operator watching the palm."""

    def __init__(self, ws_url: str) -> None:
        self.ws_url = ws_url
        self.acks: list[dict] = []
        self.palm = PalmWatch()
        self.error: BaseException | None = None
        self.done = threading.Event()
        #: set once the discarded grasp ended and two more whole grasps followed it
        self.two_more = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        try:
            with connect(self.ws_url) as ws:
                # the first grasp held on the page (the client may join one near its end)
                palm, todo, first = self.palm, sorted(MARKS.items()), None
                deadline = time.monotonic() + 60
                while (todo or len(self.acks) < len(MARKS)) and time.monotonic() < deadline:
                    msg = json.loads(ws.recv(timeout=5))
                    if msg.get("type") == "ack":
                        self.acks.append(msg)
                        continue
                    if not palm.see(msg) or not todo or palm.held_s() < CONTACT_S:
                        continue
                    first = palm.grasp if first is None else first
                    if palm.grasp - first >= todo[0][0]:
                        kind, task = todo.pop(0)[1]
                        cmd = {"type": "command", "action": "episode_mark", "kind": kind}
                        if task:
                            cmd["task"] = task
                        ws.send(json.dumps(cmd))
                self.done.set()
                # counted on the palm, however long a busy machine makes them
                last = (first or 0) + max(MARKS) + AFTER_DISCARD
                while palm.grasp < last and time.monotonic() < deadline + 60:
                    palm.see(json.loads(ws.recv(timeout=5)))
                if palm.grasp >= last:
                    self.two_more.set()
        except BaseException as e:  # reported by the test
            self.error = e
        finally:
            self.done.set()


@pytest.fixture(scope="module")
def marked_session(tmp_path_factory):
    """A demo recording, its dashboard used to mark one grasp failed and the one after next
    discarded."""
    out = tmp_path_factory.mktemp("marked")
    with DashboardDemo("--record", str(out), "--no-video") as demo:
        client = MarkingClient(demo.ws_url)
        assert client.done.wait(90), "the marking client never finished"
        assert client.two_more.wait(60) or client.error, "no two more grasps after the marks"
        code, _, stderr = demo.finish()
    assert client.error is None, repr(client.error)
    assert code == 0, stderr[-3000:]
    assert [(a["ok"], a["kind"]) for a in client.acks] == [(True, "failed"), (True, "discard")], (
        f"contact on the page (s, grasp, touching): {client.palm.changes}"
    )
    return out


def _run_export(session, out, *args):
    proc = subprocess.run(
        [
            *(sys.executable, "-m", "deploy.cli", "export", str(session), "--out", str(out)),
            *("--fps", str(FPS), "--no-progress", "--json", *args),
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout)


def _episodes(root):
    import pyarrow.parquet as pq

    return pq.read_table(root / "meta/episodes/chunk-000/file-000.parquet").to_pylist()


def test_a_grasp_marked_failed_on_the_dashboard_is_exported_as_failed(
    lerobot, marked_session, tmp_path
):
    # the marks are in the operator's recording, on their own channel
    recorded = [r for ch, _, r in read_recording(marked_session / "operator.mcap") if ch == CHANNEL]
    assert [(r["kind"], r.get("task"), r["source"]) for r in recorded] == [
        ("failed", FAILED_TASK, "dashboard"),
        ("discard", None, "dashboard"),
    ]
    (failed_mark, discard_mark), unplaced = read_marks(marked_session / "operator.mcap")
    assert unplaced == 0

    # the numbering a user sees: an export without --exclude
    first = _run_export(marked_session, tmp_path / "first")
    assert first["marks"] == {"read": 2, "unplaced": 0, "before_first_episode": 0}
    assert [e["reason"] for e in first["left_out"]] == ["discard"]
    numbered = _episodes(tmp_path / "first")
    assert len(numbered) >= 3, "the demo made too few grasps to curate"
    marked = [(e["deepxpalm/number"], e.get("deepxpalm/marks")) for e in numbered]
    assert len(first["failed_episodes"]) == 1, (
        f"the failed grasp is not one episode of its own: marks (robot ns) "
        f"{[(m.kind, m.t_robot_ns) for m in (failed_mark, discard_mark)]}, episodes {marked}, "
        f"export {first}"
    )
    [failed] = first["failed_episodes"]
    others = [e["deepxpalm/number"] for e in numbered if e["deepxpalm/number"] != failed]
    excluded, retasked = others[-1], others[0]
    (tmp_path / "tasks.toml").write_text(f'{retasked} = "{FILE_TASK}"\n')

    root = tmp_path / "curated"
    summary = _run_export(
        marked_session,
        root,
        "--exclude",
        str(excluded),
        "--task-file",
        str(tmp_path / "tasks.toml"),
    )
    assert summary["episodes"] == len(numbered) - 1
    npz = tmp_path / "loaded.npz"
    lerobot.load(root, npz)
    with np.load(npz) as z:
        a = {k: z[k] for k in z.files}
    meta = json.loads(a.pop("_meta").tobytes())
    assert meta["num_episodes"] == len(numbered) - 1
    assert meta["features"]["next.success"]["dtype"] == "bool"

    t_first = {e["deepxpalm/number"]: e["deepxpalm/t_first_ns"] for e in numbered}
    loaded_starts = [ep["deepxpalm/t_first_ns"] for ep in meta["episodes"]]
    assert t_first[excluded] not in loaded_starts
    assert sorted(loaded_starts) == sorted(t for n, t in t_first.items() if n != excluded)

    def span(ep):
        return ep["deepxpalm/t_first_ns"], ep["deepxpalm/t_first_ns"] + ep["length"] * 1e9 / FPS

    # the discarded grasp: no loaded episode holds the moment it was marked (in contact)
    assert not any(lo <= discard_mark.t_robot_ns < hi for lo, hi in map(span, meta["episodes"]))
    [failed_ep] = [
        ep for ep in meta["episodes"] if span(ep)[0] <= failed_mark.t_robot_ns < span(ep)[1]
    ]
    success = a["next.success"].reshape(-1)
    for ep in meta["episodes"]:
        rows = slice(ep["dataset_from_index"], ep["dataset_to_index"])
        tasks = set(meta["tasks"][rows])
        if ep is failed_ep:
            assert not success[rows].any()
            assert tasks == {FAILED_TASK}
            continue
        # LeRobot's convention: true on the episode's last row only
        assert success[rows].tolist() == [False] * (ep["length"] - 1) + [True]
        if ep["deepxpalm/t_first_ns"] == t_first[retasked]:
            assert tasks == {FILE_TASK}
        else:
            assert tasks == {"grasp the pipette"}
