"""The simulated lab: a MuJoCo world whose arm, gripper, pads and cameras the real drivers reach.

The world runs in-process or as its own process (``python -m robot_side.lab``);
its devices are kinds of the arm, gripper and tactile families (``devices.py``)
and its camera a kind of the camera family (``robot_side/camera/lab.py``).
docs/lab.md describes it.
"""
