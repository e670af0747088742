"""The relay: robots and operators connect out to it; ZeroMQ's proxy fans the stream out."""
