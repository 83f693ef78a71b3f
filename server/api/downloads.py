"""Downloads under a file name: the ``Content-Disposition`` of RFC 6266."""

from __future__ import annotations

import re
from urllib.parse import quote

from fastapi.responses import Response

_NOT_PLAIN = re.compile(r'[^\x20-\x7e]|["\\%]')
"""What the plain ``filename`` fallback leaves out: all but printable ASCII, and the quote,
backslash and percent sign that clients read differently (RFC 6266, appendix D)."""
_ATTR_CHARS = "!#$&+-.^_`|~"
"""What RFC 5987 leaves unencoded in ``filename*`` besides letters and digits."""


def content_disposition(name: str) -> str:
    """``attachment`` under ``name``, whatever it holds: ``filename*`` carries it exactly
    (UTF-8, percent-encoded), ``filename`` an ASCII stand-in for clients that know no other."""
    fallback = _NOT_PLAIN.sub("_", name)
    return f"attachment; filename=\"{fallback}\"; filename*=UTF-8''{quote(name, safe=_ATTR_CHARS)}"


def download(data: bytes, name: str) -> Response:
    return Response(
        data,
        media_type="application/octet-stream",
        headers={"Content-Disposition": content_disposition(name)},
    )
