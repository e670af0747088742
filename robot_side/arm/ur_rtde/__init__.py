"""UR3e through ur-rtde: RTDEReceiveInterface for state, RTDEControlInterface for motion.

What ur-rtde does when the controller goes away shapes this driver
(measured against the simulator, see docs/arm.md):

- Receive getters keep returning the last cached values. Every read
  checks ``isConnected()`` and that the controller timestamp still advances;
  otherwise it raises instead of handing out an old pose (``receive``).
- Control calls that wait for the script's "done" (speedStop, stopL, moveL,
  stopScript) retry a vanished controller forever, and realtime ones
  (speedL) report success into the void. So each control call first checks
  ``isConnected()`` and then runs on a worker thread with a deadline (ur-rtde
  releases the GIL in those calls): a stuck call becomes a
  ``DeviceTimeoutError`` and the driver is marked unusable, never a hang
  (``control``).
- The constructors hold the GIL while they talk to the controller, so a
  simulator must not share this process (the "simulated" kind runs it in a
  child process); ``connection`` probes the ports first.
- RTDEIOInterface aborts the whole process when its server vanishes: not used.

The driver (``driver.URArm``) is the :class:`~robot_side.arm.base.Arm` made
of its parts, each in a module of its own:

- ``connection``: opening both interfaces, and closing them without the
  destructor that freezes the process;
- ``receive``: the state stream, its staleness and the reads;
- ``control``: the control connection, one call on the wire at a time;
- ``keep_alive``: the controller's watchdog, armed at connect and kicked
  while this process lives, and the script it stopped noticed;
- ``motion``: jogs, moves and stops with their accelerations.
"""

from robot_side.arm.ur_rtde.config import STOP_BUDGET_S, URArmConfig
from robot_side.arm.ur_rtde.connection import CONTROLLER_PORTS, RECEIVE_VARIABLES
from robot_side.arm.ur_rtde.control import ArmCommandRefusedError
from robot_side.arm.ur_rtde.driver import URArm
from robot_side.arm.ur_rtde.keep_alive import WatchdogArmingLostError

__all__ = [
    "CONTROLLER_PORTS",
    "RECEIVE_VARIABLES",
    "STOP_BUDGET_S",
    "ArmCommandRefusedError",
    "URArm",
    "URArmConfig",
    "WatchdogArmingLostError",
]
