"""Upload limits: the body size as ASGI middleware (413 before the body is parsed),
and :class:`UploadLimits`, what the intake (:func:`service.worker.stage_upload`)
checks before it spends memory or CPU on an upload.

A declared ``Content-Length`` above the limit is refused without being stored
(read and dropped up to ``DRAIN_BYTES``, so that the client gets the answer); a
body sent without one (chunked) is counted while it streams and refused when
it passes the limit. The limit is read from the running app's settings.
"""

from __future__ import annotations

import json
from dataclasses import dataclass

from fastapi import HTTPException

__all__ = ["UploadLimitMiddleware", "UploadLimits"]


@dataclass(frozen=True)
class UploadLimits:
    """What one upload may hold (``Settings.upload_limits()``; docs/SERVICE.md, "Limits and refusals").

    Every limit is checked from headers (zip directory, PNG ``IHDR``, video
    container) before the data it describes is unpacked or decoded.
    """

    body_bytes: int  # the request body
    unpacked_bytes: int  # a zip's members, summed (declared sizes, and counted while extracting)
    max_frames: int  # frames per camera: frame numbers of PNG names, a video's frame count
    max_cameras: int  # cameras in rig.json, videos per upload
    max_image_side: int  # width and height of a frame, a PNG and rig.json's image_size
    max_image_pixels: int  # width x height of the same
    decoded_bytes: int  # PNG pixels of a sequence folder, summed (what reading it holds in memory)
    max_json_bytes: int = 16 << 20  # rig.json, truth.json

    def image_refusal(self, width: int, height: int) -> str | None:
        """Why a ``width`` x ``height`` image is too large, or None if it is not."""
        if width > self.max_image_side or height > self.max_image_side:
            return f"{width}x{height} exceeds the largest side of {self.max_image_side} pixels"
        if width * height > self.max_image_pixels:
            return f"{width}x{height} exceeds the limit of {self.max_image_pixels} pixels"
        return None


class UploadLimitMiddleware:
    """Limit the request body of ``POST`` requests under ``prefix``."""

    def __init__(self, app, prefix: str = "/v1/jobs") -> None:
        self.app = app
        self.prefix = prefix

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] != "http" or scope["method"] != "POST" or not scope["path"].startswith(self.prefix):
            await self.app(scope, receive, send)
            return
        limit = scope["app"].state.settings.upload_limit_bytes
        headers = dict(scope.get("headers") or [])
        declared = headers.get(b"content-length")
        if declared is not None and declared.isdigit() and int(declared) > limit:
            await _drain(receive, DRAIN_BYTES)
            await _reject(send, f"upload of {int(declared)} bytes exceeds the limit of {limit} bytes")
            return
        seen = 0

        async def counting_receive():
            nonlocal seen
            message = await receive()
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > limit:
                    raise HTTPException(413, f"upload exceeds the limit of {limit} bytes")
            return message

        await self.app(scope, counting_receive, send)


DRAIN_BYTES = 32 << 20
"""A refused upload's body is read (and dropped) up to this much before the 413 is sent: a client
still sending when the connection closes sees a reset, not the answer. A larger body gets the
answer and the close after this much (its sender may then see the reset)."""


async def _drain(receive, cap: int) -> None:
    """Read and drop the request body, at most ``cap`` bytes of it."""
    seen = 0
    while seen <= cap:
        message = await receive()
        if message["type"] != "http.request":
            return
        seen += len(message.get("body", b""))
        if not message.get("more_body", False):
            return


async def _reject(send, reason: str) -> None:
    body = json.dumps({"detail": reason}).encode()
    await send({"type": "http.response.start", "status": 413,
                "headers": [(b"content-type", b"application/json"),
                            (b"content-length", str(len(body)).encode()),
                            (b"connection", b"close")]})
    await send({"type": "http.response.body", "body": body})
