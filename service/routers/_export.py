"""The export formats of results and live calibrations as REST answers (``?format=``)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from fastapi import HTTPException, Response

from ..exports import MEDIA_TYPES

__all__ = ["export_content", "export_response"]


def export_content(*formats: str) -> dict[str, Any]:
    """OpenAPI ``content`` for the text formats a route answers besides its JSON."""
    return {MEDIA_TYPES[f]: {"schema": {"type": "string"}} for f in formats}


def export_response(make: Callable[[], str], fmt: str, filename: str) -> Response:
    """``make()``'s text as ``fmt`` (its media type, as an attachment named ``filename``); 400 with the
    reason when the data cannot give that format (``make`` raises ValueError)."""
    try:
        text = make()
    except ValueError as exc:
        raise HTTPException(400, f"format {fmt!r}: {exc}") from None
    return Response(text, media_type=MEDIA_TYPES[fmt],
                    headers={"Content-Disposition": f'attachment; filename="{filename}"'})
