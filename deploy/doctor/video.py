"""Is the video server the robot carries viewers' offers to there, on this PC?"""

from __future__ import annotations

import importlib.util
from typing import Any

from common.devices.preflight import FAIL, PASS
from deploy.doctor.report import DoctorOptions, Report


def check_video(report: Report, config: Any, options: DoctorOptions) -> None:
    """With ``link.video_url`` set: websockets importable and the URL accepting connections."""
    url = config.link.video_url
    if not url:
        return
    name = "video server"
    if importlib.util.find_spec("websockets") is None:
        report.add(
            name,
            FAIL,
            "link.video_url is set but websockets is not installed",
            "pip install '.[video]' on the robot PC",
        )
        return
    from websockets.exceptions import InvalidStatus
    from websockets.sync.client import connect

    from common.web import web_token
    from robot_side.video.link_signalling import LinkSignalling

    shown = web_token.without_token(url)
    try:
        signalling_url = LinkSignalling(url, token_file=config.link.video_token_file).url()
        with connect(signalling_url, open_timeout=options.tcp_timeout_s * 3):
            pass
    except InvalidStatus as e:
        report.add(
            name,
            FAIL,
            f"{shown} refused the robot's token (HTTP {e.response.status_code}); viewers "
            "would get no picture",
            "set link.video_token_file to the video server's token_file (or put the token "
            "deepxpalm video printed in link.video_url)",
        )
        return
    except (OSError, TimeoutError, ValueError) as e:
        report.add(
            name,
            FAIL,
            f"nothing answers at {shown} ({type(e).__name__}: {e}); viewers would get "
            "'no video server' instead of a picture",
            "start `deepxpalm video` on this PC with that port, or leave link.video_url empty",
        )
        return
    report.add(name, PASS, f"{shown} accepts viewers' offers (carried over the link)")
