"""Compile (or load) every cached numba function the robot node uses, once, now.

numba keeps the machine code it compiles next to the sources (``robot_side/jit/cache.py``),
and a robot node compiles what is missing when it starts: about 4 s for each
process that starts before the cache exists, all of them at once when several
start together. ``python -m robot_side.node.jit_warm`` compiles it in one process:
an install step for a robot PC (its first start is then as quick as every
other), and the test suite's before its lanes, so parallel workers load the
cache instead of each compiling the same functions.

Each part is built as the node builds it (the classifier's numba backend, the
compiled frame step for the mask mode, the serial board's scan conversion),
so the signatures compiled are the node's own. Without numba (the robot
extra) there is nothing to compile, and that is said.
"""

from __future__ import annotations

import sys
import time

import numpy as np


def warm() -> list[str]:
    """What was compiled or loaded from the cache; raises if numba is missing."""
    import numba  # noqa: F401  (the robot extra)

    from common.tactile.contract import FRAME_SHAPE
    from robot_side.node.compiled_step import CompiledFrameStep
    from robot_side.node.config import RenderConfig
    from robot_side.perception import load_classifier
    from robot_side.tactile.board_calibration import BoardCalibration
    from robot_side.tactile.serial_board import ScanConverter, SerialTactileConfig

    done = []
    classifier = load_classifier(backend="numba")  # the single-frame pass, at load
    classifier.predict(np.zeros((2, *FRAME_SHAPE), np.float32))  # the batch pass
    done.append("classifier (numba)")
    if CompiledFrameStep.for_node(classifier, RenderConfig()) is not None:
        done.append("compiled frame step (mask mode)")
    ScanConverter(BoardCalibration.uniform(0.0, 1.0), SerialTactileConfig())
    done.append("serial scan conversion")
    return done


def main() -> int:
    t0 = time.monotonic()
    try:
        done = warm()
    except ImportError as e:
        print(f"nothing to compile: {e} (numba is in the robot extra)", file=sys.stderr)
        return 0
    from robot_side.jit.cache import cache_counts

    loaded, compiled = cache_counts()
    print(
        f"{', '.join(done)}: {loaded} loaded from the cache, {compiled} compiled "
        f"({time.monotonic() - t0:.1f} s)"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
