"""The relay passes an observer's STOP (and nothing else of an observer's) on to the robot."""

from __future__ import annotations

from common.codec import encode
from common.messages import Command
from relay_side.relay import _is_arm_stop


def test_only_an_arm_stop_is_read_as_one_whatever_the_bytes():
    def cmd(action: str, **kw) -> bytes:
        return encode(Command(seq=1, t_send_ns=2, action=action, **kw), b"cell1")

    assert _is_arm_stop(cmd("arm_stop"))
    assert _is_arm_stop(encode(Command(seq=1, t_send_ns=2, action="arm_stop")))  # unnamed robot
    for other in ("arm_resume", "arm_jog_end", "gripper_open", "lease_request"):
        assert not _is_arm_stop(cmd(other))
    assert not _is_arm_stop(cmd("arm_jog", velocity=(0.1, 0, 0, 0, 0, 0)))
    stop = cmd("arm_stop")
    for n in range(len(stop)):  # a cut or garbled frame is never a stop, and never raises
        assert not _is_arm_stop(stop[:n]) or n == len(stop)
    assert not _is_arm_stop(b"CMND\x05cell1\xc1\xc1")
