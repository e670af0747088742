"""The operator node as a package: one module per concern, the node itself assembles and loops.

- ``operator_node``: ``OperatorNode``, receive -> render -> send each loop turn;
- ``link_setup``: the robot's name, the keys and their policy, the sockets;
- ``arrivals``: what the robot sends, believed or dropped (its key, the
  telemetry gate: ``telemetry_gate``), the clock sync and the link
  statistics; ``RobotHeard``: when the robot was last heard, and its run;
- ``lease_view``: the robot's control lease as its heartbeat states it;
- ``palm``: the stimulus to render, the servo goals, the latency;
- ``outbox``: commands and video signals to the robot (late and blind jogs
  dropped, gripper commands resent until confirmed, video signals held);
- ``heartbeat``: the heartbeat out; ``operator_channels``: every channel the node
  records; ``snapshot``: what the live views show (a ``Snapshot``, declared
  by the views in ``operator_side.dashboard.snapshot``); ``config``: the
  node's typed config; ``build``: ``build_operator_node`` from a config.
"""

from common.clocks.late_wake import LATE_WAKE_NS
from operator_side.node.arrivals import RESTART_SEQ_GAP
from operator_side.node.build import build_operator_node
from operator_side.node.operator_node import OperatorNode
from operator_side.node.outbox import VIDEO_HOLD_NS
from operator_side.node.palm import LIFT_ARRIVAL_S

__all__ = [
    "LATE_WAKE_NS",
    "LIFT_ARRIVAL_S",
    "RESTART_SEQ_GAP",
    "VIDEO_HOLD_NS",
    "OperatorNode",
    "build_operator_node",
]
