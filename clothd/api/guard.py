"""The API's front door, an ASGI middleware in front of everything else, so that nothing it refuses is
ever parsed, authenticated against, or allowed near the loop (docs/api.md, "Security").

In order, for every HTTP request and WebSocket handshake:
1. Host must be one of the daemon's own names (loopback, plus `api.allowed_hosts`): a page that
   reaches it through DNS rebinding carries its own domain here. Else 421.
2. A request that changes anything (POST, PUT, PATCH, DELETE) and every WebSocket must come from the
   daemon's own origin or one in `api.allowed_origins`: Origin, or the Referer's origin when there is
   no Origin. A client that sends neither (curl, a PLC) is no web page. Else 403.
3. A body must be JSON (Content-Type application/json), so no cross-site "simple" request reaches a
   route. Else 415.
4. With `api.token`, a changing request must carry it (compared in constant time). Else 401.
5. A body larger than `api.max_body_bytes` is refused from its Content-Length before a byte is read,
   and a streamed one as soon as it passes the limit. Else 413. The body is read whole here, before the
   app: one that trickles in costs no routing and no handler.
Refusals are short JSON bodies that never echo what was sent.
"""

from __future__ import annotations

import hmac
import json
from collections.abc import Awaitable, Callable, MutableMapping
from dataclasses import dataclass
from typing import Any
from urllib.parse import urlsplit

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]

LOOPBACK_NAMES = ("127.0.0.1", "localhost", "[::1]")
CHANGING_METHODS = frozenset({"POST", "PUT", "PATCH", "DELETE"})


@dataclass(frozen=True)
class GuardPolicy:
    port: int
    allowed_hosts: tuple[str, ...] = ()  # more names the daemon answers to (no port)
    allowed_origins: tuple[str, ...] = ()  # more origins that may change things: scheme://host[:port]
    token: str | None = None
    max_body_bytes: int = 4096

    def host_ok(self, host: str) -> bool:
        name, port = _split_host(host.lower())  # host names are case-insensitive (RFC 3986 3.2.2)
        names = (*LOOPBACK_NAMES, *(h.lower() for h in self.allowed_hosts))
        return name in names and port in ("", str(self.port))

    def origin_ok(self, origin: str, host: str) -> bool:
        return origin.lower() == f"http://{host.lower()}" or origin in self.allowed_origins

    def token_problem(self, authorization: str) -> str | None:
        """Why the Authorization header does not carry the token (None: it does, or none is needed). A
        missing token and a wrong one are told apart: the first is a client set up without it, the
        second one holding another daemon's or an old token."""
        if self.token is None:
            return None
        if not authorization:
            return "this daemon needs Authorization: Bearer <token>"
        scheme, _, given = authorization.partition(" ")
        if scheme.lower() != "bearer":
            return "the Authorization header must be Bearer <token>"
        if not hmac.compare_digest(given.encode(), self.token.encode()):
            return "the bearer token is not this daemon's (api.token)"
        return None


def _split_host(host: str) -> tuple[str, str]:
    """A Host header's name and port ("" when none): "[::1]:8080" -> ("[::1]", "8080")."""
    if host.startswith("["):
        name, _, rest = host.partition("]")
        return name + "]", rest.removeprefix(":")
    name, _, port = host.partition(":")
    return name, port


def _origin_of(url: str) -> str:
    parts = urlsplit(url)
    return f"{parts.scheme}://{parts.netloc}"


class RequestGuard:
    def __init__(self, app: ASGIApp, policy: GuardPolicy) -> None:
        self.app = app
        self.policy = policy

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket"):
            await self.app(scope, receive, send)
            return
        refusal = self._refusal(scope)
        if refusal is not None:
            await _refuse(scope, receive, send, *refusal)
            return
        if scope["type"] == "websocket":
            await self.app(scope, receive, send)
            return
        # The body is read here, whole and bounded, before the app sees the request: a body that trickles
        # in, or never ends, costs no routing and no handler, and is dropped with its connection.
        limit = self.policy.max_body_bytes
        body = bytearray()
        more = True
        while more:
            message = await receive()
            if message["type"] == "http.disconnect":
                return  # gone before its request was whole: nobody to answer
            body += message.get("body", b"")
            if len(body) > limit:
                await _refuse(scope, receive, send, 413, f"a request body is at most {limit} bytes")
                return
            more = message.get("more_body", False)
        replayed = False

        async def replay() -> Message:
            nonlocal replayed
            if replayed:
                return await receive()  # after the body: the disconnect a streaming response waits for
            replayed = True
            return {"type": "http.request", "body": bytes(body), "more_body": False}

        await self.app(scope, replay, send)

    def _refusal(self, scope: Scope) -> tuple[int, str] | None:
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope["headers"]}
        host = headers.get("host", "")
        p = self.policy
        if not p.host_ok(host):
            return 421, "this daemon answers to its own host names only (api.allowed_hosts)"
        changing = scope["type"] == "websocket" or scope["method"] in CHANGING_METHODS
        if not changing:
            return None
        origin = headers.get("origin") or (_origin_of(headers["referer"]) if "referer" in headers else None)
        if origin is not None and not p.origin_ok(origin, host):
            return 403, "requests from another origin are refused (api.allowed_origins)"
        if scope["type"] == "websocket":
            return None
        length = headers.get("content-length", "0")
        has_body = length != "0" or "transfer-encoding" in headers
        media = headers.get("content-type", "").split(";")[0].strip().lower()
        if has_body and media != "application/json":
            return 415, "a request body must be application/json"
        token_problem = p.token_problem(headers.get("authorization", ""))
        if token_problem is not None:
            return 401, token_problem
        if not length.isdigit():
            return 400, "a bad Content-Length"
        if int(length) > p.max_body_bytes:
            return 413, f"a request body is at most {p.max_body_bytes} bytes"
        return None


async def _refuse(scope: Scope, receive: Receive, send: Send, status: int, detail: str) -> None:
    if scope["type"] == "websocket":
        await receive()  # the handshake's websocket.connect
        await send({"type": "websocket.close", "code": 1008, "reason": detail})
        return
    body = json.dumps({"detail": detail}).encode()
    headers = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]
    if status == 401:
        headers.append((b"www-authenticate", b"Bearer"))
    await send({"type": "http.response.start", "status": status, "headers": headers})
    await send({"type": "http.response.body", "body": body})
