"""REST access: bearer tokens with scopes, checked from the request's headers before anything else.

With ``api_token`` or ``api_token_file`` set (:meth:`service.settings.Settings.api_tokens`)
every ``/v1`` request, and ``/metrics`` unless ``metrics_open``, needs
``Authorization: Bearer <token>``; otherwise the answer is 401 with
``WWW-Authenticate: Bearer``. A token may carry scopes (:data:`SCOPES`): ``read``
(GET), ``submit`` (POST a job, and read), ``admin`` (cancel and delete, and
everything); a token without the scope a request needs gets 403 with the reason.
``/healthz``, ``/docs`` and ``/openapi.json`` stay open. An ASGI middleware rather
than a dependency: FastAPI reads a request's form body before it solves
dependencies, so a stranger's upload would be spooled before being refused;
here it is refused from the headers.
"""

from __future__ import annotations

import hmac
from dataclasses import dataclass

from starlette.responses import JSONResponse
from starlette.types import ASGIApp, Receive, Scope, Send

__all__ = ["SCOPES", "ApiToken", "BearerAuthMiddleware", "match_token", "parse_token_line", "required_scope"]

# Each scope and what it grants: a wider scope includes the narrower ones.
SCOPES: dict[str, frozenset[str]] = {
    "read": frozenset({"read"}),
    "submit": frozenset({"read", "submit"}),
    "admin": frozenset({"read", "submit", "admin"}),
}
ALL_SCOPES = SCOPES["admin"]


@dataclass(frozen=True)
class ApiToken:
    """One accepted bearer token and the scopes it grants (expanded: submit includes read)."""

    secret: bytes
    scopes: frozenset[str] = ALL_SCOPES


def parse_token_line(line: str) -> ApiToken:
    """``TOKEN`` (every scope) or ``TOKEN SCOPE[,SCOPE...]`` (read, submit, admin);
    ValueError naming an unknown scope."""
    token, *rest = line.split(None, 1)
    names = " ".join(rest).replace(",", " ").split()
    if not names:
        return ApiToken(token.encode())
    unknown = [n for n in names if n not in SCOPES]
    if unknown:
        raise ValueError(f"unknown API token scope {unknown[0]!r} (scopes: {', '.join(SCOPES)})")
    return ApiToken(token.encode(), frozenset().union(*(SCOPES[n] for n in names)))


def required_scope(method: str, path: str, prefix: str = "/v1") -> str:
    """The scope a request needs: reading (GET, HEAD) needs ``read``, submitting a job
    (POST ``/v1/jobs``) ``submit``, anything else (cancel, delete) ``admin``."""
    if method in ("GET", "HEAD"):
        return "read"
    if method == "POST" and path.rstrip("/") == f"{prefix}/jobs":
        return "submit"
    return "admin"


def match_token(authorization: str | None, tokens: tuple[ApiToken, ...]) -> ApiToken | None:
    """The token an ``Authorization`` header value carries, or None.

    Compared in constant time against every token, so neither a token's content nor
    which one matched shows in the answer's timing.
    """
    scheme, _, given = (authorization or "").partition(" ")
    candidate = given.strip().encode() if scheme.lower() == "bearer" else b""
    found = None
    for token in tokens:
        if hmac.compare_digest(candidate, token.secret) and found is None:
            found = token
    return found

class BearerAuthMiddleware:
    """Refuse unauthenticated requests to the guarded paths (401), and requests whose token
    lacks the scope they need (403), before the app sees them.

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
        if not tokens:
            await self.app(scope, receive, send)
            return
        headers = dict(scope.get("headers") or [])
        value = headers.get(b"authorization")
        token = match_token(value.decode("latin-1") if value is not None else None, tokens)
        if token is None:
            response = JSONResponse({"detail": "missing or wrong bearer token (Authorization: Bearer <token>)"},
                                    status_code=401, headers={"WWW-Authenticate": "Bearer"})
        else:
            method, path = scope.get("method", "GET"), scope.get("path", "")
            need = required_scope(method, path, self.prefix)
            if need in token.scopes:
                await self.app(scope, receive, send)
                return
            response = JSONResponse(
                {"detail": f"this token may not {method} {path}: that needs the {need!r} scope, the token "
                           f"has {', '.join(s for s in SCOPES if s in token.scopes)}"},
                status_code=403, headers={"WWW-Authenticate": f'Bearer error="insufficient_scope", scope="{need}"'})
        await response(scope, receive, send)
