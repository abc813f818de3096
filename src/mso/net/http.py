"""The little HTTP/1.1 the dashboard and the metrics endpoint speak, on asyncio's streams: read
one bounded request, write one response, close. No keep-alive, no chunking; enough for a page,
a JSON API, an event stream and a Prometheus scrape, without a web framework."""

from __future__ import annotations

import asyncio

MAX_HEADER = 8192
REASONS = {200: "OK", 400: "Bad Request", 403: "Forbidden", 404: "Not Found", 405:
           "Method Not Allowed", 409: "Conflict", 413: "Payload Too Large", 415:
           "Unsupported Media Type", 431: "Request Header Fields Too Large", 502: "Bad Gateway",
           503: "Service Unavailable"}  # fmt: skip


class BadRequest(Exception):
    """Answered with ``status`` and the message; the connection is closed after it."""

    def __init__(self, status: int, message: str) -> None:
        super().__init__(message)
        self.status = status


async def read_request(
    reader: asyncio.StreamReader, max_body: int = 4096
) -> tuple[str, str, dict[str, str], bytes]:
    """Method, target, headers (lower-case names) and body of one request."""
    try:
        head = await reader.readuntil(b"\r\n\r\n")
    except asyncio.LimitOverrunError:
        raise BadRequest(431, "request header too large") from None
    if len(head) > MAX_HEADER:
        raise BadRequest(431, "request header too large")
    lines = head.decode("latin-1").split("\r\n")
    parts = lines[0].split(" ")
    if len(parts) != 3 or not parts[2].startswith("HTTP/1."):
        raise BadRequest(400, "bad request line")
    headers: dict[str, str] = {}
    for line in lines[1:]:
        if line:
            k, sep, v = line.partition(":")
            if not sep:
                raise BadRequest(400, "bad header line")
            headers[k.strip().lower()] = v.strip()
    try:
        length = int(headers.get("content-length", "0"))
    except ValueError:
        raise BadRequest(400, "bad Content-Length") from None
    if length < 0 or length > max_body:
        raise BadRequest(413, f"body larger than {max_body} bytes")
    body = await reader.readexactly(length) if length else b""
    return parts[0], parts[1], headers, body


def response(status: int, ctype: str, body: bytes, extra: str = "") -> bytes:
    """A whole response; ``extra`` is more header lines, each ending in CRLF."""
    head = (
        f"HTTP/1.1 {status} {REASONS.get(status, 'Error')}\r\nContent-Type: {ctype}\r\n"
        f"Content-Length: {len(body)}\r\nCache-Control: no-store\r\n"
        f"X-Content-Type-Options: nosniff\r\n{extra}Connection: close\r\n\r\n"
    )
    return head.encode() + body
