"""UR3e arm: the interface, the ur-rtde driver and a wire-level UR simulator.

``KINDS`` maps a scene's ``kind`` to the class that implements it; a kind a
scene does not name is never imported. "simulated" is the real ur-rtde
driver talking to an in-process simulator on a loopback address; "memory"
is the safety layer over a driver that only records (tests, benches).
"""

KINDS = {
    "ur_rtde": "robot_side.arm.process.kinds:URArmKind",
    "simulated": "robot_side.arm.sim:SimulatedArmKind",
    "lab": "robot_side.lab.devices:LabArmKind",
    "memory": "robot_side.arm.memory:MemoryArm",
}
