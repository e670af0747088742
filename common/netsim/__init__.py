"""A latency simulator between the robot and the operator.

Linux netem needs root and a kernel module; this runs anywhere, as a thread
in a test or as ``deepxpalm netsim``, and impairs each direction of the
link independently: as a TCP byte forwarder (stream mode, CURVE passes) or as
a ZeroMQ re-publisher (message mode). See docs/netsim.md.
"""
