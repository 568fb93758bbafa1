"""Upload size limit as ASGI middleware: 413 before the body is parsed.

A declared ``Content-Length`` above the limit is refused at once; a body sent
without one (chunked) is counted while it streams and refused when it passes
the limit. The limit is read from the running app's settings.
"""

from __future__ import annotations

import json

from fastapi import HTTPException

__all__ = ["UploadLimitMiddleware"]


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


async def _reject(send, reason: str) -> None:
    body = json.dumps({"detail": reason}).encode()
    await send({"type": "http.response.start", "status": 413,
                "headers": [(b"content-type", b"application/json"),
                            (b"content-length", str(len(body)).encode()),
                            (b"connection", b"close")]})
    await send({"type": "http.response.body", "body": body})
