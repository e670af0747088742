"""A message-level latency simulator between the robot and the operator.

Linux netem needs root and a kernel module; this runs anywhere, as a thread
in a test or as ``deepxpalm netsim``, and impairs each direction of the
ZeroMQ link independently. See docs/netsim.md.
"""
