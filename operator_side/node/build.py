"""``build_operator_node``: the operator node from its config, its servo bus built by kind."""

from __future__ import annotations

import zmq

from common.devices.lifecycle import build_device
from common.recording.channels import Recorder
from operator_side.node.config import OperatorConfig
from operator_side.node.operator_node import OperatorNode


def build_operator_node(
    config: OperatorConfig, ctx: zmq.Context | None = None, recorder: Recorder | None = None
) -> OperatorNode:
    from operator_side.servos import KINDS

    servos = build_device(KINDS, config.servos, "operator.servos")
    return OperatorNode(config, servos, ctx=ctx, recorder=recorder)
