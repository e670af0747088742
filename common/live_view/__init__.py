"""A live view in Foxglove: server.py serves it, session_files.py feeds it a session's files."""
