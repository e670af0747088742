"""numba on the robot side: ``cache.njit``, the compiler every kernel goes through.

The kernels live with what they compute (``perception/numba_forward.py``,
``tactile/compiled.py``, ``node/compiled_step.py``); ``python -m
robot_side.node.jit_warm`` compiles them all once. Importing this package
imports nothing: numba is in the robot extra.
"""
