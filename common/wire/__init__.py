"""The wire between the nodes: its messages, their codec and signatures, the sockets.

messages.py (docs/protocol.md), codec.py and codec_schema.py (validated both
ways), signing.py and replay_window.py (Ed25519 end to end, once and in order),
transport.py (ZeroMQ), capture_link.py (a node's link as its callers see it),
connection_watch.py, loopback_ports.py, link_stats.py (a stream's statistics at
its receiver), ice.py (the video call's STUN/TURN servers).
"""
