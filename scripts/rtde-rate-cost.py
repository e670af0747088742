"""What ur-rtde's two interfaces cost the robot PC, at a given RTDE rate.

    python scripts/rtde-rate-cost.py [RATE_HZ ...]   # default: 500 125

For each rate: a receive interface (the variables the driver streams) and a
control interface, both at that rate, connected to the UR simulator (its own
process, the controller's wire protocol), left idle for 1 s and measured for
5 s. Prints the CPU seconds per second of this process (ur-rtde's threads:
nothing else runs in it) and of the simulator's.

ur-rtde's receive threads poll their socket every 100 us until a package
arrives, for up to 2 ms, then read blocking: at 500 Hz a package comes every
2 ms and they never block; at 125 Hz they poll 2 ms of every 8.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from harness.processes import process_cpu_s
from robot_side.arm.sim.process import URSimProcess
from robot_side.arm.ur_rtde import RECEIVE_VARIABLES

SETTLE_S = 1.0
WINDOW_S = 5.0


def measure(sim: URSimProcess, rate_hz: float) -> None:
    import rtde_control
    import rtde_receive

    recv = rtde_receive.RTDEReceiveInterface(sim.host, rate_hz, RECEIVE_VARIABLES)
    ctrl = rtde_control.RTDEControlInterface(sim.host, rate_hz)
    try:
        time.sleep(SETTLE_S)
        own0, sim0 = process_cpu_s(os.getpid()), process_cpu_s(sim.pid)
        time.sleep(WINDOW_S)
        own1, sim1 = process_cpu_s(os.getpid()), process_cpu_s(sim.pid)
    finally:
        ctrl.stopScript()
        ctrl.disconnect()
        recv.disconnect()
    print(
        f"{rate_hz:6.0f} Hz: driver {(own1 - own0) / WINDOW_S:.3f} CPU s/s, "
        f"simulator {(sim1 - sim0) / WINDOW_S:.3f} CPU s/s",
        flush=True,
    )


def main() -> None:
    rates = [float(a) for a in sys.argv[1:]] or [500.0, 125.0]
    with URSimProcess() as sim:
        for rate in rates:
            measure(sim, rate)
            time.sleep(SETTLE_S)  # the controller frees the inputs when it sees the close
    # ur-rtde's destructors sleep holding the interpreter (docs/arm.md): leave without them
    os._exit(0)


if __name__ == "__main__":
    main()
