"""What the nodes record and how: MCAP files Foxglove opens.

channels.py: what is recorded and the recorder's interface; mcap_recorder.py,
mcap_channels.py, mcap_json.py write it, mcap_reader.py reads it back;
foxglove.py and foxglove_schemas.py: Foxglove's types; episode_marks.py: the
operator's word on an episode.
"""
