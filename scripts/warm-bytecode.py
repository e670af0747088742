"""Import the heavy third-party packages once, so their bytecode is written once.

``make setup`` installs with ``--no-compile`` (compiling every file of every
package took 31 of the install's 58 s), so Python compiles a module the first
time something imports it and keeps the result. On a fresh clone the test
lanes' first processes (four workers, then the nodes, simulators and browsers
they start) would all compile torch, SciPy, aiortc, MuJoCo ... at the same
moment: about 5 s more CPU each than with the bytecode there. One process
before the lanes compiles only what is imported, once. A package that is
not installed is skipped, so this runs on any role's install.
"""

from __future__ import annotations

import importlib
import time

#: what the suite's processes import between them, heaviest first
PACKAGES = (
    "torch",
    "scipy.signal",
    "matplotlib.pyplot",
    "mujoco",
    "aiortc",
    "av",
    "numba",
    "onnxruntime",
    "websockets",
    "zmq",
    "msgpack",
)


def main() -> None:
    t0 = time.monotonic()
    done = []
    for name in PACKAGES:
        try:
            importlib.import_module(name)
        except ImportError:
            continue
        done.append(name)
    print(f"bytecode written for {', '.join(done)} ({time.monotonic() - t0:.1f} s)")


if __name__ == "__main__":
    main()
