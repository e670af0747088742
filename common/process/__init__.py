"""A node's process: its command line, systemd's notify protocol, signals, real-time threads."""
