"""Robotiq 2F gripper: the interface, the URCap socket and Modbus RTU drivers, the simulator.

``KINDS`` maps a scene's ``kind`` to the class that implements it; a kind a
scene does not name is never imported. "simulated" is the real socket
driver talking to an in-process simulator over loopback TCP; "memory" keeps
the registers in memory (tests, benches).
"""

KINDS = {
    "robotiq_socket": "robot_side.gripper.urcap_socket:RobotiqSocketGripper",
    "robotiq_rtu": "robot_side.gripper.modbus_rtu:RobotiqRtuGripper",
    "simulated": "robot_side.gripper.sim:SimulatedGripper",
    "lab": "robot_side.lab.devices:LabGripper",
    "memory": "robot_side.gripper.memory:MemoryGripper",
}
