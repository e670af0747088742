"""A camera's rows as a LeRobot video feature: one MP4 per file index, episodes back to back.

LeRobot v3 keeps each camera in ``videos/<feature>/chunk-000/file-000.mp4``
with the episodes one after another; an episode's metadata says where its
frames start (``from_timestamp``) and end, and the loader decodes frame
``from_timestamp + timestamp`` of a row. So the video holds exactly one
frame per row, frame *n* of the file at *n* / fps: the camera picture the
row holds (sample and hold, as every observation), coded as LeRobot codes
its own (``libsvtav1``, ``yuv420p``, a keyframe every 2 frames, CRF 30), or
as H.264 (``libx264``).

Statistics are LeRobot's for images: per channel, over pixels, in 0..1
(shape 3x1x1), from every 8th pixel of each row's picture.
"""

from __future__ import annotations

import os
import threading
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np

from common.errors import DeepXPalmError

VIDEO_PATH = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
CODEC_NAMES = {"libsvtav1": "av1", "libx264": "h264"}
STATS_STRIDE = 8
#: how long an encoder may take to flush its last pictures and close the file
FLUSH_TIMEOUT_S = 60.0


def encoder_options(codec: str) -> dict[str, str]:
    """LeRobot's settings (encode_video_frames): a keyframe every 2 frames, CRF 30."""
    if codec == "libsvtav1":
        return {"g": "2", "crf": "30", "preset": "10"}
    return {"g": "2", "crf": "23", "preset": "veryfast"}


class VideoFeatureWriter:
    """Appends one picture per row to the current MP4 of ``name``; new file past ``file_mb``."""

    def __init__(
        self,
        root: Path,
        name: str,
        width: int,
        height: int,
        fps: int,
        codec: str = "libx264",
        file_mb: float = 200.0,
    ) -> None:
        os.environ.setdefault("SVT_LOG", "1")  # SVT-AV1 prints its banner on stderr otherwise
        self.root, self.name = Path(root), name
        self.width, self.height, self.fps, self.codec = width, height, fps, codec
        self.file_bytes = file_mb * 1e6
        self.file_index = 0
        self._container: Any = None
        self._stream: Any = None
        self._n = 0  # frames in the current file
        self._last: tuple[bytes, Any, np.ndarray] | None = None  # held JPEG, frame, stats pixels

    @property
    def path(self) -> Path:
        return self.root / VIDEO_PATH.format(
            video_key=self.name, chunk_index=self.file_index // 1000, file_index=self.file_index
        )

    def begin_episode(self) -> dict[str, Any]:
        """Open a file when none is, or a new one past the size limit; where the episode starts."""
        # the muxer creates the file with its first packet: an encoder still filling its
        # lookahead (a short first episode) has written nothing yet
        if (
            self._container is not None
            and self.path.exists()
            and self.path.stat().st_size > self.file_bytes
        ):
            self._close()
            self.file_index += 1
        if self._container is None:
            self._open()
        return {
            f"videos/{self.name}/chunk_index": self.file_index // 1000,
            f"videos/{self.name}/file_index": self.file_index % 1000,
            f"videos/{self.name}/from_timestamp": self._n / self.fps,
        }

    def add(self, jpeg: bytes) -> np.ndarray:
        """Code the row's picture; returns its stats pixels (N x 3, in 0..1)."""
        import av

        if self._last is None or self._last[0] is not jpeg:
            rgb = _decode_jpeg(jpeg)
            frame = av.VideoFrame.from_ndarray(rgb, format="rgb24")
            if rgb.shape[:2] != (self.height, self.width):  # a camera that changed size
                frame = frame.reformat(width=self.width, height=self.height)
                rgb = frame.to_ndarray(format="rgb24")
            pixels = rgb[::STATS_STRIDE, ::STATS_STRIDE].reshape(-1, 3) / 255.0
            self._last = (jpeg, frame.reformat(format="yuv420p"), pixels)
        _, picture, pixels = self._last
        out = av.VideoFrame.from_ndarray(picture.to_ndarray(), format="yuv420p")
        out.pts = self._n
        for packet in self._stream.encode(out):
            self._container.mux(packet)
        self._n += 1
        return pixels

    def end_episode(self) -> dict[str, Any]:
        return {f"videos/{self.name}/to_timestamp": self._n / self.fps}

    def finish(self) -> None:
        if self._container is not None:
            self._close()

    def info(self) -> dict[str, Any]:
        """The feature's ``info`` as LeRobot writes it in meta/info.json."""
        return {
            "video.height": self.height,
            "video.width": self.width,
            "video.codec": CODEC_NAMES[self.codec],
            "video.pix_fmt": "yuv420p",
            "video.is_depth_map": False,
            "video.fps": self.fps,
            "video.channels": 3,
            "has_audio": False,
        }

    def _open(self) -> None:
        import av

        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._container = av.open(str(self.path), "w")
        stream = self._container.add_stream(self.codec, rate=self.fps)
        stream.width, stream.height, stream.pix_fmt = self.width, self.height, "yuv420p"
        stream.time_base = Fraction(1, self.fps)
        stream.options = encoder_options(self.codec)
        self._stream = stream
        self._n = 0

    def _close(self) -> None:
        """Flush the encoder and close the file; an encoder that never returns is an error.

        SVT-AV1 has known deadlocks (its flush waited on its own threads forever
        once, CPU idle, in one of about twenty exports of the test suite's runs).
        The flush runs on a thread of its own; one that is not done in
        ``FLUSH_TIMEOUT_S`` is abandoned with the file, and the export fails
        with what to do instead of hanging.
        """
        failed: list[BaseException] = []

        def flush() -> None:
            try:
                for packet in self._stream.encode():
                    self._container.mux(packet)
                self._container.close()
            except BaseException as e:  # raised again in the caller's thread
                failed.append(e)

        flushing = threading.Thread(target=flush, name=f"{self.name}-flush", daemon=True)
        flushing.start()
        flushing.join(FLUSH_TIMEOUT_S)
        if flushing.is_alive():
            raise DeepXPalmError(
                f"the {CODEC_NAMES[self.codec]} encoder did not finish {self.path} in "
                f"{FLUSH_TIMEOUT_S:.0f} s (SVT-AV1 has known deadlocks): export again, or "
                'export with video_codec = "libx264"'
            )
        if failed:
            raise failed[0]
        self._container = self._stream = None


def _decode_jpeg(data: bytes) -> np.ndarray:
    from robot_side.video.camera_recording import decode_jpeg

    return decode_jpeg(data)
