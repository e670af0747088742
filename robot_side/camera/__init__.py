"""Cameras on the robot PC: the interface, the V4L2 driver, the test pattern, the lab's camera.

``KINDS`` maps the video config's ``source`` to the class that implements
it; a kind the config does not name is never imported (the V4L2 kind needs
PyAV only when it opens). Each kind's typed config is in ``config.py``, so
the video config can describe every kind without importing one.
``robot_side/video`` streams whichever camera is built here.
"""

KINDS = {
    "test_pattern": "robot_side.camera.test_pattern:TestPatternCamera",
    "v4l2": "robot_side.camera.v4l2:V4L2Camera",
    "lab": "robot_side.camera.lab:LabCamera",
}
