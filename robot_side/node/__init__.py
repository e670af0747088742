"""The robot node as a package: one module per concern, the node itself only a loop.

- ``robot_node``: ``RobotNode``, receive -> step -> write each loop turn;
- ``frame_pipeline``: ``FramePipeline``, the whole frame rule (rate cap,
  stale frames, skips, dead band, keyframes), called by the node, replay
  and the skipping bench alike; ``frame_rule``: ``render_frame``, the rule
  for one frame, and the renderer that applies it (plain, or in one
  compiled call: ``compiled_step``);
- ``command_desk``: ``CommandDesk``, the one admission of every operator
  message, signed or not (``peers``), by the rules in ``commands/`` (the
  command gate, the lease, the stop latch); ``pending_stops``: the stops
  that wait for their sender's proof; ``handover``: the stop latch, the
  hand-over to the device workers and the ``robot/command`` recording;
  ``device_calls``, the table from action to device call; ``assist``: the
  reflex the desk holds for the lease holder;
- ``workers``: the devices' worker threads and recoveries (from
  ``robot_side.devices``); ``deadman``; ``telemetry``: heartbeats and
  display frames; ``video_desk``: viewers' signalling; ``link_setup``: name,
  signing key and sockets; ``build``: ``build_robot_node`` from a config;
  ``jit_warm``: the node's numba functions compiled once (``python -m
  robot_side.node.jit_warm``).
"""

from robot_side.node.build import build_robot_node
from robot_side.node.command_desk import CommandDesk
from robot_side.node.frame_pipeline import FramePipeline
from robot_side.node.frame_rule import (
    Classifier,
    Prediction,
    RenderSettings,
    compiled_step_for,
    render_frame,
)
from robot_side.node.robot_node import RobotNode
from robot_side.node.workers import ARM_ENVELOPE_KEYS, ARM_RECONNECT_MAX_BACKOFF_S

__all__ = [
    "ARM_ENVELOPE_KEYS",
    "ARM_RECONNECT_MAX_BACKOFF_S",
    "Classifier",
    "CommandDesk",
    "FramePipeline",
    "Prediction",
    "RenderSettings",
    "RobotNode",
    "build_robot_node",
    "compiled_step_for",
    "render_frame",
]
