"""The rules an operator's message must pass before the node acts on it.

- ``command_gate``: ``CommandGate``, fresh by the sender's clock, in order,
  once, of this robot run;
- ``lease``: ``ControlLease``, which one operator key the robot acts on and
  how it changes hands;
- ``stop_latch``: ``StopLatch``, an ``arm_stop`` holds until the holder
  resumes.

Plain rules over messages and keys: nothing here touches a device or a
socket. The node's ``command_desk`` applies them to every message.
"""
