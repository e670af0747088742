"""How the robot side runs its devices, whatever the device.

- ``device_worker``: one thread per device, so the frame loop never waits on
  one, the newest request winning;
- ``recovery``: a failed device brought back on a thread of its own;
- ``device_state_recorder``: the arm's and the gripper's state in a recording;
- ``stdio_child``: a simulator in a child process, asked over stdin/stdout.

The devices themselves are in ``arm``, ``gripper``, ``camera``, ``tactile``
and the simulated ``lab``.
"""
