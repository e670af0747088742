"""An encoder that never finishes its file fails the export with what to do, not a hang."""

from __future__ import annotations

import threading

import pytest

from common.errors import DeepXPalmError
from deploy.export import video


class _HungStream:
    """An encoder whose flush waits forever, as SVT-AV1's once did on its own threads."""

    def __init__(self) -> None:
        self.release = threading.Event()

    def encode(self, frame=None):
        self.release.wait()
        return []


class _Container:
    closed = False

    def mux(self, packet) -> None:
        pass

    def close(self) -> None:
        self.closed = True


def _writer(tmp_path, stream) -> video.VideoFeatureWriter:
    writer = video.VideoFeatureWriter(tmp_path, "observation.images.overview", 64, 48, 10)
    writer._container, writer._stream = _Container(), stream
    return writer


def test_a_flush_that_never_returns_is_an_error_naming_the_way_out(tmp_path, monkeypatch):
    monkeypatch.setattr(video, "FLUSH_TIMEOUT_S", 0.2)
    stream = _HungStream()
    try:
        with pytest.raises(
            DeepXPalmError, match='export again, or export with video_codec = "libx264"'
        ):
            _writer(tmp_path, stream).finish()
    finally:
        stream.release.set()


def test_a_flush_that_returns_closes_the_file(tmp_path):
    stream = _HungStream()
    stream.release.set()
    writer = _writer(tmp_path, stream)
    container = writer._container
    writer.finish()
    assert container.closed and writer._container is None
