"""A live view in Foxglove: server.py serves it, recordings.py feeds it a session's files."""
