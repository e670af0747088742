"""The relay: robots and operators connect out to it; its XPUBs fan the stream out."""
