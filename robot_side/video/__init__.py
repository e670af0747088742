"""Video from the robot PC to the operator's browser over WebRTC.

``source.py`` is the interface every camera implements (a V4L2 camera, the
test pattern, a simulated lab's rendered camera); ``server.py`` answers a
browser's WebRTC offer (relayed by the operator's dashboard) and streams
one source to every connected viewer. Nothing is captured or encoded while
no viewer is connected. Needs the ``video`` extra (aiortc).
"""
