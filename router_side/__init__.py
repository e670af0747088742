"""The fabric's router: a Zenoh router whose access control is made from the roster."""
