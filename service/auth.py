"""REST access: bearer tokens, checked from the request's headers before anything else.

With ``api_token`` or ``api_token_file`` set (:meth:`service.settings.Settings.api_tokens`)
every ``/v1`` request, and ``/metrics`` unless ``metrics_open``, needs
``Authorization: Bearer <token>``; otherwise the answer is 401 with
``WWW-Authenticate: Bearer``. ``/healthz``, ``/docs`` and ``/openapi.json`` stay
open. An ASGI middleware rather than a dependency: FastAPI reads a request's
form body before it solves dependencies, so a stranger's upload would be
spooled before being refused; here it is refused from the headers.
"""

from __future__ import annotations

import hmac

from starlette.responses import JSONResponse
from starlette.types import ASGIApp, Receive, Scope, Send

__all__ = ["BearerAuthMiddleware", "token_accepted"]


def token_accepted(authorization: str | None, tokens: tuple[bytes, ...]) -> bool:
    """Whether an ``Authorization`` header value carries one of ``tokens`` (none: always).

    Compared in constant time against every token, so neither a token's content nor
    which one matched shows in the answer's timing.
    """
    if not tokens:
        return True
    scheme, _, given = (authorization or "").partition(" ")
    candidate = given.strip().encode() if scheme.lower() == "bearer" else b""
    matched = False
    for token in tokens:
        matched |= hmac.compare_digest(candidate, token)
    return matched


class BearerAuthMiddleware:
    """Refuse unauthenticated requests to the guarded paths (401) before the app sees them.

    Reads the tokens from ``app.state.runtime`` and ``metrics_open`` from
    ``app.state.settings``, both set by the lifespan.
    """

    def __init__(self, app: ASGIApp, *, prefix: str = "/v1") -> None:
        self.app, self.prefix = app, prefix

    def _guarded(self, scope: Scope) -> bool:
        path: str = scope.get("path", "")
        if path == self.prefix or path.startswith(self.prefix + "/"):
            return True
        settings = getattr(scope["app"].state, "settings", None)
        return path == "/metrics" and not (settings is not None and settings.metrics_open)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or not self._guarded(scope):
            await self.app(scope, receive, send)
            return
        runtime = getattr(scope["app"].state, "runtime", None)
        tokens = runtime.api_tokens if runtime is not None else ()
        headers = dict(scope.get("headers") or [])
        value = headers.get(b"authorization")
        if token_accepted(value.decode("latin-1") if value is not None else None, tokens):
            await self.app(scope, receive, send)
            return
        response = JSONResponse({"detail": "missing or wrong bearer token (Authorization: Bearer <token>)"},
                                status_code=401, headers={"WWW-Authenticate": "Bearer"})
        await response(scope, receive, send)
