"""Tactile pads: the interface, the serial board driver and the simulators.

``KINDS`` maps a scene's ``kind`` to the class that implements it; a kind a
scene does not name is never imported.
"""

KINDS = {
    "scripted": "robot_side.tactile.scripted:ScriptedTactileSensor",
    "serial": "robot_side.tactile.serial_board:SerialTactileSensor",
    "simulated_serial": "robot_side.tactile.board_sim:SimulatedSerialTactileSensor",
    "lab": "robot_side.lab.devices:LabTactileSensor",
}
