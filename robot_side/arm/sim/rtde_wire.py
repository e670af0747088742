"""RTDE protocol 2 on the wire, as the UR controller serves it on port 30004.

Every message is ``uint16 size | uint8 type | payload``, big-endian, with
``size`` counting the 3-byte header. A client negotiates the protocol
version, asks the controller version, sets up one output recipe (variable
names and a frequency) and any number of input recipes (names), then starts
the stream: the controller sends data packages of the output recipe, the
client sends data packages of an input recipe whenever it wants.

The variable table below is the controller's: a name the table lacks is
answered ``NOT_FOUND``, exactly as the real controller does, so a client
asking for something this simulator does not model fails the same way.
"""

from __future__ import annotations

import struct

HEADER = struct.Struct(">HB")

REQUEST_PROTOCOL_VERSION = ord("V")
GET_URCONTROL_VERSION = ord("v")
TEXT_MESSAGE = ord("M")
DATA_PACKAGE = ord("U")
SETUP_OUTPUTS = ord("O")
SETUP_INPUTS = ord("I")
START = ord("S")
PAUSE = ord("P")

MESSAGE_NAMES = {
    REQUEST_PROTOCOL_VERSION: "REQUEST_PROTOCOL_VERSION",
    GET_URCONTROL_VERSION: "GET_URCONTROL_VERSION",
    TEXT_MESSAGE: "TEXT_MESSAGE",
    DATA_PACKAGE: "DATA_PACKAGE",
    SETUP_OUTPUTS: "SETUP_OUTPUTS",
    SETUP_INPUTS: "SETUP_INPUTS",
    START: "START",
    PAUSE: "PAUSE",
}

#: RTDE type name -> struct format (without byte order).
TYPE_FORMATS = {
    "BOOL": "?",
    "UINT8": "B",
    "UINT32": "I",
    "UINT64": "Q",
    "INT32": "i",
    "DOUBLE": "d",
    "VECTOR3D": "3d",
    "VECTOR6D": "6d",
    "VECTOR6INT32": "6i",
    "VECTOR6UINT32": "6I",
}

NOT_FOUND = "NOT_FOUND"
IN_USE = "IN_USE"


def _output_table() -> dict[str, str]:
    t = {
        "timestamp": "DOUBLE",
        "actual_execution_time": "DOUBLE",
        "robot_mode": "INT32",
        "joint_mode": "VECTOR6INT32",
        "safety_mode": "INT32",
        "safety_status": "INT32",
        "actual_tool_accelerometer": "VECTOR3D",
        "speed_scaling": "DOUBLE",
        "target_speed_fraction": "DOUBLE",
        "actual_momentum": "DOUBLE",
        "actual_main_voltage": "DOUBLE",
        "actual_robot_voltage": "DOUBLE",
        "actual_robot_current": "DOUBLE",
        "actual_joint_voltage": "VECTOR6D",
        "actual_digital_input_bits": "UINT64",
        "actual_digital_output_bits": "UINT64",
        "runtime_state": "UINT32",
        "elbow_position": "VECTOR3D",
        "elbow_velocity": "VECTOR3D",
        "robot_status_bits": "UINT32",
        "safety_status_bits": "UINT32",
        "analog_io_types": "UINT32",
        "standard_analog_input0": "DOUBLE",
        "standard_analog_input1": "DOUBLE",
        "standard_analog_output0": "DOUBLE",
        "standard_analog_output1": "DOUBLE",
        "io_current": "DOUBLE",
        "euromap67_input_bits": "UINT32",
        "euromap67_output_bits": "UINT32",
        "euromap67_24V_voltage": "DOUBLE",
        "euromap67_24V_current": "DOUBLE",
        "tool_mode": "UINT32",
        "tool_analog_input_types": "UINT32",
        "tool_analog_input0": "DOUBLE",
        "tool_analog_input1": "DOUBLE",
        "tool_output_voltage": "INT32",
        "tool_output_current": "DOUBLE",
        "tool_temperature": "DOUBLE",
        "tcp_force_scalar": "DOUBLE",
        "output_bit_registers0_to_31": "UINT32",
        "output_bit_registers32_to_63": "UINT32",
        "input_bit_registers0_to_31": "UINT32",
        "input_bit_registers32_to_63": "UINT32",
        "tool_output_mode": "UINT8",
        "tool_digital_output0_mode": "UINT8",
        "tool_digital_output1_mode": "UINT8",
        "payload": "DOUBLE",
        "payload_cog": "VECTOR3D",
        "payload_inertia": "VECTOR6D",
        "script_control_line": "UINT32",
        "ft_raw_wrench": "VECTOR6D",
        "joint_position_deviation_ratio": "VECTOR6D",
        "collision_detection_ratio": "DOUBLE",
        "time_scale_source": "UINT32",
    }
    for name in (
        "target_q",
        "target_qd",
        "target_qdd",
        "target_current",
        "target_moment",
        "actual_q",
        "actual_qd",
        "actual_current",
        "actual_current_window",
        "joint_control_output",
        "actual_TCP_pose",
        "actual_TCP_speed",
        "actual_TCP_force",
        "target_TCP_pose",
        "target_TCP_speed",
        "joint_temperatures",
        "actual_current_as_torque",
    ):
        t[name] = "VECTOR6D"
    for i in range(64, 128):
        t[f"output_bit_register_{i}"] = "BOOL"
        t[f"input_bit_register_{i}"] = "BOOL"
    for i in range(48):
        t[f"output_int_register_{i}"] = "INT32"
        t[f"output_double_register_{i}"] = "DOUBLE"
        t[f"input_int_register_{i}"] = "INT32"
        t[f"input_double_register_{i}"] = "DOUBLE"
    return t


def _input_table() -> dict[str, str]:
    t = {
        "speed_slider_mask": "UINT32",
        "speed_slider_fraction": "DOUBLE",
        "standard_digital_output_mask": "UINT8",
        "standard_digital_output": "UINT8",
        "configurable_digital_output_mask": "UINT8",
        "configurable_digital_output": "UINT8",
        "tool_digital_output_mask": "UINT8",
        "tool_digital_output": "UINT8",
        "standard_analog_output_mask": "UINT8",
        "standard_analog_output_type": "UINT8",
        "standard_analog_output_0": "DOUBLE",
        "standard_analog_output_1": "DOUBLE",
        "input_bit_registers0_to_31": "UINT32",
        "input_bit_registers32_to_63": "UINT32",
        "external_force_torque": "VECTOR6D",
    }
    for i in range(64, 128):
        t[f"input_bit_register_{i}"] = "BOOL"
    for i in range(48):
        t[f"input_int_register_{i}"] = "INT32"
        t[f"input_double_register_{i}"] = "DOUBLE"
    return t


OUTPUT_TYPES = _output_table()
INPUT_TYPES = _input_table()


def pack_message(msg_type: int, payload: bytes = b"") -> bytes:
    return HEADER.pack(HEADER.size + len(payload), msg_type) + payload


def recipe_struct(types: list[str]) -> struct.Struct:
    """The struct of a data package's values (after the recipe id byte)."""
    return struct.Struct(">" + "".join(TYPE_FORMATS[t] for t in types))


def flatten(values: list[object]) -> list[object]:
    """Vectors become their items, as ``struct.pack`` wants them."""
    out: list[object] = []
    for v in values:
        if isinstance(v, (list, tuple)):
            out.extend(v)
        else:
            out.append(v)
    return out


def unflatten(types: list[str], flat: tuple[object, ...]) -> list[object]:
    out: list[object] = []
    i = 0
    for t in types:
        n = {"VECTOR3D": 3, "VECTOR6D": 6, "VECTOR6INT32": 6, "VECTOR6UINT32": 6}.get(t, 1)
        out.append(list(flat[i : i + n]) if n > 1 else flat[i])
        i += n
    return out


def text_message(message: str, source: str = "URSim", level: int = 1) -> bytes:
    """A protocol-2 text message (level 0 exception .. 3 info)."""
    m, s = message.encode()[:255], source.encode()[:255]
    return pack_message(TEXT_MESSAGE, bytes([len(m)]) + m + bytes([len(s)]) + s + bytes([level]))
