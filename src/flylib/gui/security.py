"""What keeps other web pages out of ``flylib gui``: the request checks, free of FastAPI.

A browser lets any page send requests to ``localhost``; these checks stop them: ``Host`` must name
the server itself (against DNS rebinding); ``Origin``, when sent, must be the server's own and
``Sec-Fetch-Site`` not ``cross-site``; every mutating request carries the session's random token
(a header, or a WebSocket sub-protocol), which the page gets inside its own HTML; bodies are JSON
(a form or ``text/plain`` POST needs no CORS pre-flight), of bounded size and depth."""

from __future__ import annotations

import hmac
import json
import re
from collections.abc import Iterable
from typing import Any

#: The largest request body or WebSocket message accepted (an edit is ~150 bytes).
MAX_BODY = 64 * 1024
#: The deepest JSON nesting accepted (an edit is two levels deep).
MAX_DEPTH = 8
#: Sent with every response: no inline script, nothing from elsewhere, never framed.
SECURITY_HEADERS = {
    "Content-Security-Policy": (
        "default-src 'none'; script-src 'self'; style-src 'self'; img-src 'self' blob: data:; "
        "connect-src 'self'; font-src 'self'; base-uri 'none'; form-action 'none'; "
        "frame-ancestors 'none'"
    ),
    "X-Content-Type-Options": "nosniff",
    "X-Frame-Options": "DENY",
    "Referrer-Policy": "no-referrer",
    "Cross-Origin-Opener-Policy": "same-origin",
    "Cross-Origin-Resource-Policy": "same-origin",
}
#: The page's WebSocket sub-protocol; the token travels as a second one (no headers on a WebSocket).
WS_PROTOCOL = "flylib.v1"
WS_TOKEN_PREFIX = "flylib.token."
LOOPBACK_NAMES = ("localhost", "127.0.0.1", "[::1]", "::1")

_STRING = re.compile(rb'"(?:[^"\\]|\\.)*"', re.DOTALL)


class RequestRefused(ValueError):
    """A request the GUI refuses; ``status`` is the HTTP status to answer with."""

    def __init__(self, status: int, message: str):
        super().__init__(message)
        self.status = status


def split_host(host: str) -> tuple[str, int | None]:
    """``"name:port"`` (or ``"[::1]:port"``) as ``(name, port)``; the name lower-cased."""
    host = host.strip().lower()
    match = re.fullmatch(r"(\[[0-9a-f:.]+\]|[^:\[\]]*)(?::(\d{1,5}))?", host)
    if not match:
        return host, None
    return match.group(1), (int(match.group(2)) if match.group(2) else None)


class RequestGuard:
    """The Host / Origin / token checks of one server; ``hosts=None`` (any) only with
    ``guard_reads`` (the token on every request, which a rebinding page does not have)."""

    def __init__(
        self,
        token: str,
        hosts: Iterable[str] | None = LOOPBACK_NAMES,
        port: int | None = None,
        guard_reads: bool = False,
    ):
        self.token = token
        self.hosts = (
            None
            if hosts is None
            else {f"[{h}]" if ":" in h and not h.startswith("[") else h.lower() for h in hosts}
        )
        self.port = port
        self.guard_reads = guard_reads

    def token_matches(self, supplied: str | None) -> bool:
        return supplied is not None and hmac.compare_digest(
            supplied.encode("utf-8", "replace"), self.token.encode()
        )

    def check_origin(self, headers: Any) -> None:
        """``Host`` and ``Origin`` (when sent) are this server's; else :class:`RequestRefused` 403."""
        host = headers.get("host") or ""
        name, port = split_host(host)
        known = self.hosts is None or name in self.hosts
        if not known or (self.port is not None and port != self.port):
            raise RequestRefused(
                403,
                f"refused: Host {host[:80]!r} is not this server; open flylib gui at the "
                "address it printed",
            )
        if headers.get("sec-fetch-site") == "cross-site":
            raise RequestRefused(403, "refused: a request from another site")
        origin = headers.get("origin")
        if origin is not None and origin.lower() not in (f"http://{host}", f"https://{host}"):
            raise RequestRefused(
                403,
                f"refused: a request from another origin ({origin[:80]!r}); flylib gui "
                "answers only its own page",
            )

    def check_mutation_token(self, supplied: str | None) -> None:
        if not self.token_matches(supplied):
            raise RequestRefused(
                403,
                "refused: missing or wrong session token (X-Flylib-Token); reload the page "
                "flylib gui printed",
            )

    def ws_token(self, protocols: Iterable[str], query_token: str | None) -> str | None:
        """The token a WebSocket handshake offers (a sub-protocol, or ``?token=``)."""
        for item in protocols:
            if item.startswith(WS_TOKEN_PREFIX):
                return item[len(WS_TOKEN_PREFIX) :]
        return query_token


def check_json_content_type(content_type: str | None) -> None:
    """Only ``application/json`` (a ``text/plain`` or form POST needs no pre-flight); else 415."""
    media = (content_type or "").split(";")[0].strip().lower()
    if media != "application/json":
        raise RequestRefused(
            415, f"refused: Content-Type {media or 'none'!r}; send application/json"
        )


def parse_json(body: bytes, what: str = "the body") -> Any:
    """``body`` as JSON; refused 413 when too large (never echoed), 400 when bad or too deep."""
    if len(body) > MAX_BODY:
        raise RequestRefused(413, f"refused: {what} is larger than {MAX_BODY // 1024} KiB")
    depth = json_depth(body)
    if depth > MAX_DEPTH:
        raise RequestRefused(400, f"refused: {what} nests deeper than {MAX_DEPTH} levels")
    try:
        return json.loads(body)
    except (ValueError, RecursionError):
        raise RequestRefused(400, f"refused: {what} is not valid JSON") from None


def json_depth(body: bytes) -> int:
    """The deepest ``[``/``{`` nesting of a JSON text (brackets inside strings ignored)."""
    depth = deepest = 0
    for char in _STRING.sub(b'""', body):
        if char in b"[{":
            depth += 1
            deepest = max(deepest, depth)
        elif char in b"]}":
            depth -= 1
    return deepest
