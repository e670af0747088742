"""The dashboard page's side of a video session, in Python: what a browser does.

aiortc sends a ``video_offer`` over the dashboard's WebSocket, as
``video.js`` does, takes the ``video_answer`` and decodes frames from the
track; a stamped frame's capture time is read back.
"""

from __future__ import annotations

import asyncio
import json

from robot_side.camera.stamp import read_stamp


async def watch_video(page_ws: str, frames: int) -> dict:
    """Offer over the dashboard's socket, then decode ``frames`` frames.

    Returns ``{"answer": ..., "stamps": [...], "frames": [rgb, ...], "answer_s": ...,
    "first_frame_s": ...}`` (the seconds from the offer to its answer and to the first
    decoded frame), or ``{"closed": reason}`` when the dashboard says the video closed.
    """
    from aiortc import RTCConfiguration, RTCPeerConnection, RTCSessionDescription
    from websockets.asyncio.client import connect

    pc = RTCPeerConnection(RTCConfiguration(iceServers=[]))  # as the page: host candidates
    pc.addTransceiver("video", direction="recvonly")
    track_future: asyncio.Future = asyncio.get_running_loop().create_future()
    pc.on("track", lambda track: track_future.done() or track_future.set_result(track))
    await pc.setLocalDescription(await pc.createOffer())
    stamps, images = [], []
    loop = asyncio.get_running_loop()
    try:
        # every message buffered, as a browser's socket does: the dashboard pushes its state
        # ~20 times a second and this page reads only the video's; with websockets' default
        # of 16 frames the socket stopped reading, and its close waited out the 10 s
        # close_timeout behind the unread state (measured under an observer's flood)
        async with connect(page_ws, max_size=2**22, max_queue=None) as ws:
            await ws.send(json.dumps({"type": "video_offer", "sdp": pc.localDescription.sdp}))
            t_offer = loop.time()
            while True:
                msg = json.loads(await asyncio.wait_for(ws.recv(), 20))
                if msg["type"] in ("video_answer", "video_closed"):
                    break
            if msg["type"] == "video_closed":
                return {"closed": msg["reason"]}
            answer_s = loop.time() - t_offer
            first_frame_s = None
            await pc.setRemoteDescription(RTCSessionDescription(msg["sdp"], "answer"))
            track = await asyncio.wait_for(track_future, 20)
            for _ in range(frames):
                frame = await asyncio.wait_for(track.recv(), 30)
                if first_frame_s is None:
                    first_frame_s = loop.time() - t_offer
                rgb = frame.to_ndarray(format="rgb24")
                images.append(rgb)
                stamp = read_stamp(rgb)
                if stamp is not None:
                    stamps.append(stamp)
        return {
            "answer": msg,
            "stamps": stamps,
            "frames": images,
            "answer_s": answer_s,
            "first_frame_s": first_frame_s,
        }
    finally:
        await pc.close()
