"""The fault matrix: the deployed processes killed, frozen and restarted, measured from outside.

``deployment`` starts the processes as on the real machines (the fabric's
router, robot, operator, link simulator, video, recorder, and every device
simulator in a process of its own) and plays systemd for the shipped units;
``probes``
reads the arm from the UR simulator's wire, the gripper from its socket and
the palm from the servo bus's front panel; ``matrix`` injects one fault per
cell and turns what the probes saw into a row of docs/robustness.md.
"""
