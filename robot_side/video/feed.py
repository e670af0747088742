"""One capture loop per camera, shared by the viewers' stream and the session's recording.

A camera is read by one thread only: ``capture()`` blocks at the camera's
own pace, and a V4L2 device cannot be opened twice. Whoever needs frames
subscribes here; the loop connects the camera when the first subscriber
arrives and disconnects it when the last one leaves, so a camera (or a
simulated lab's renderer) still works only while someone watches or records.
Consumers take the newest frame (a slow viewer skips frames rather than
queueing them); listeners (the recorder) are handed every frame on the
capture thread and must return at once.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

from robot_side.camera.base import Camera, CapturedFrame

log = logging.getLogger(__name__)

RETRY_S = 1.0  # after a camera error, while someone still wants frames


class CameraFeed:
    """``subscribe``/``unsubscribe`` open and close the camera; ``next_frame`` waits for one."""

    def __init__(self, camera: Camera) -> None:
        self.camera = camera
        self._cond = threading.Condition()
        self._users: dict[str, int] = {}
        self._listeners: list[Callable[[CapturedFrame], None]] = []
        self._seq = 0
        self._latest: CapturedFrame | None = None
        self._error: BaseException | None = None
        self._closed = False
        self.frames = 0
        self._thread = threading.Thread(target=self._run, name="camera-feed", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------ consumers
    def subscribe(self, who: str) -> None:
        """``who`` wants frames (``viewer``, ``recording``): the camera opens if it was closed."""
        with self._cond:
            self._users[who] = self._users.get(who, 0) + 1
            self._cond.notify_all()

    def unsubscribe(self, who: str) -> None:
        with self._cond:
            self._users[who] = self._users.get(who, 0) - 1
            if self._users[who] <= 0:
                del self._users[who]
            self._cond.notify_all()

    def add_listener(self, listener: Callable[[CapturedFrame], None]) -> None:
        with self._cond:
            self._listeners.append(listener)

    def remove_listener(self, listener: Callable[[CapturedFrame], None]) -> None:
        with self._cond:
            self._listeners.remove(listener)

    def next_frame(self, after: int, timeout_s: float) -> tuple[int, CapturedFrame] | None:
        """The newest frame numbered above ``after`` (and its number); None after ``timeout_s``.

        Raises the camera's error when it failed since the caller's last frame.
        """
        with self._cond:
            if not self._cond.wait_for(
                lambda: self._seq > after or self._error is not None or self._closed, timeout_s
            ):
                return None
            if self._seq > after and self._latest is not None:
                return self._seq, self._latest
            if self._error is not None:
                raise self._error
            return None

    @property
    def closed(self) -> bool:
        """``close()`` was called: no frame will come."""
        return self._closed

    def close(self, timeout_s: float = 5.0) -> None:
        """End the loop (the camera is disconnected); waits at most ``timeout_s`` for it."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()
        self._thread.join(timeout_s)

    # ------------------------------------------------------------ the loop
    def _wanted(self) -> bool:
        return bool(self._users) and not self._closed

    def _run(self) -> None:
        while True:
            with self._cond:
                self._cond.wait_for(lambda: self._wanted() or self._closed)
                if self._closed:
                    return
                who = ", ".join(sorted(self._users))
            try:
                self.camera.connect()
            except Exception as e:  # reported to every consumer, retried
                self._failed(e)
                continue
            log.info("video: %s opened for a %s", self.camera.name, who)
            try:
                self._capture_while_wanted()
            except Exception as e:
                self._failed(e)
            finally:
                try:
                    self.camera.disconnect()
                except Exception:
                    log.exception("video: %s did not disconnect cleanly", self.camera.name)
            with self._cond:
                if not self._users:
                    log.info("video: %s closed (no viewers)", self.camera.name)

    def _capture_while_wanted(self) -> None:
        while True:
            with self._cond:
                if not self._wanted():
                    return
                listeners = list(self._listeners)
            frame = self.camera.capture()
            with self._cond:
                self._seq += 1
                self._latest = frame
                self._error = None
                self.frames += 1
                self._cond.notify_all()
            for listener in listeners:
                listener(frame)

    def _failed(self, e: BaseException) -> None:
        log.warning("video: %s failed: %s (retrying while wanted)", self.camera.name, e)
        with self._cond:
            self._error = e
            self._cond.notify_all()
            self._cond.wait_for(lambda: self._closed, RETRY_S)
