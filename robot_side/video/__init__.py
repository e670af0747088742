"""Video from the robot PC to the operator's browser over WebRTC.

The cameras are a device family of their own (``robot_side/camera``: a
V4L2 camera, the test pattern, a simulated lab's rendered camera);
``server.py`` answers a browser's WebRTC offer (relayed by the operator's
dashboard) and streams one camera to every connected viewer. Nothing is captured or encoded while
no viewer is connected. Needs the ``video`` extra (aiortc).
"""
