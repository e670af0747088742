"""Shared by both nodes: wire schemas and codec, transport, config, clocks.

Nothing in this package may import torch: the operator node imports it.
"""
