"""Shared by the nodes, the router and the tools, one room per concern.

wire/ (messages, codec, signatures, sockets), keys/ (CURVE keys, the roster),
clocks/, config/, tactile/ (the contract, the stimulus), recording/ (MCAP),
live_view/ (Foxglove), devices/, process/ (command line, systemd, signals),
web/ (the browser-facing servers), fabric/ (the Zenoh side), netsim/ (the link
simulator); errors.py, logs.py, progress.py, rotation.py at the bottom.

Nothing in this package may import torch: the operator node imports it.
"""
