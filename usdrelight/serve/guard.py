"""Who may talk to the web app, checked in the opening handshake of viser's server; and the upload bounds,
applied to each message before viser sees it.

Rules (a refusal is HTTP 403 with one line of text, before anything of the scene is sent):

* ``Host`` must name this server: one Host header, a name in :attr:`Guard.names` (127.0.0.1, localhost, ::1
  and the ``--host`` given; for a non-loopback ``--host`` also the machine's own names and any IP literal,
  which no DNS rebinding can produce) and the port the request arrived on.
* ``Origin``, when present (browsers always send it on a WebSocket), must be that same origin:
  ``http://`` + the request's Host. A WebSocket without an Origin (a script, not a browser) must carry the
  token.
* A widget change may set only the widget's value (see :func:`screen`).
* The token (a random secret per run, :attr:`Guard.token`) is required on every request, on loopback too (a
  browser sends an honest Origin, but any local program, another user's included, can send whatever Origin it
  likes): the printed URL carries it as ``?token=...``; the page's response sets it as an HttpOnly,
  SameSite=Strict cookie (``usdrelight-serve-PORT``) that the page's own requests (the WebSocket included) then
  carry.

viser (1.1) builds its server inside a background thread with ``websockets.asyncio.server.serve`` and passes
its own ``process_request`` (the static files), offering no hook of its own. :func:`guarded` therefore
replaces that one name for the moment ViserServer is being built, with a subclass of ``serve`` that puts
:meth:`Guard.check` before viser's ``process_request`` and uses a connection class whose ``recv`` screens
file-transfer messages through :class:`usdrelight.serve.uploads.UploadGate`. If viser stops building its
server that way, :func:`guarded` raises instead of serving unguarded (``tests/test_serve_security.py`` checks
it against the installed viser).
"""
from __future__ import annotations

import asyncio
import contextlib
import functools
import hmac
import http
import inspect
import ipaddress
import logging
import secrets
import socket
import threading
import time
from http.cookies import CookieError, SimpleCookie
from urllib.parse import parse_qs, urlsplit

import msgspec
import websockets.asyncio.server as ws_server

from ..errors import UsdRelightError
from .uploads import CLOSE, DROP, PASS, UploadGate

log = logging.getLogger(__name__)
LOOPBACK_NAMES = ("127.0.0.1", "localhost", "::1")
#: viser's message type names for an upload and a widget change (``type`` field of its msgpack messages).
UPLOAD_START, UPLOAD_PART, GUI_UPDATE = "FileTransferStartUpload", "FileTransferPart", "GuiUpdateMessage"
LOG_EVERY = 10.0
"""Seconds between two logged refusals (the others are counted)."""
MAX_FRAME_BYTES = 2 << 20
"""Largest message a client may send (viser's browser sends uploads in 512 KiB parts; its own limit, 50 MB, lets
one frame of empty arrays decode into ~80 times its size in Python objects)."""
_install_lock = threading.Lock()


def is_loopback(host: str) -> bool:
    name = str(host).strip("[]").lower()
    if name == "localhost":
        return True
    try:
        return ipaddress.ip_address(name).is_loopback
    except ValueError:
        return False


def _ip_literal(name: str) -> bool:
    try:
        ipaddress.ip_address(name)
        return True
    except ValueError:
        return False


def _host_port(text: str, default_port: int = 80) -> tuple[str, int] | None:
    """(lower-case name without brackets, port) of a Host header value or an origin's netloc, or None."""
    if not text or any(c in text for c in "/?#@ \t\\"):
        return None
    try:
        parts = urlsplit("//" + text)
        name, port = parts.hostname, parts.port
    except ValueError:
        return None
    return (name, port if port is not None else default_port) if name else None


class Guard:
    """The request rules of one server (see the module docstring)."""

    def __init__(self, host: str, gate: UploadGate | None = None):
        self.loopback = is_loopback(host)
        self.token = secrets.token_urlsafe(24)
        self.token_required = True  # on loopback too: any local program can send a page's Origin header
        self.names = set(LOOPBACK_NAMES) | {str(host).strip("[]").lower()}
        if not self.loopback:
            self.names |= {socket.gethostname().lower(), socket.getfqdn().lower()}
        self.gate = gate
        self.refusals = 0
        self.installed = False
        self._logged = float("-inf")  # time of the last refusal logged (a page can send many)

    @staticmethod
    def cookie_name(port: int) -> str:
        return f"usdrelight-serve-{port}"

    def _name_ok(self, name: str) -> bool:
        return name in self.names or (not self.loopback and _ip_literal(name))

    def _token_in(self, request, port: int) -> tuple[bool, bool]:
        """(the request carries the token, it came in the URL's query)."""
        query = parse_qs(urlsplit(request.path).query).get("token", [])
        if any(hmac.compare_digest(q.encode(), self.token.encode()) for q in query):
            return True, True
        cookie = SimpleCookie()
        try:
            cookie.load("; ".join(request.headers.get_all("Cookie")))
        except CookieError:
            return False, False
        morsel = cookie.get(self.cookie_name(port))
        return morsel is not None and hmac.compare_digest(morsel.value.encode(), self.token.encode()), False

    def refusal(self, request, port: int) -> str:
        """Why ``request`` (a websockets Request that arrived on ``port``) is refused; '' when it is not."""
        headers = request.headers
        hosts = headers.get_all("Host")
        host = _host_port(hosts[0]) if len(hosts) == 1 else None
        if host is None or not self._name_ok(host[0]) or host[1] != port:
            return f"Host {hosts[0][:80] if hosts else None!r} is not this server"
        origins = headers.get_all("Origin")
        websocket = any("websocket" in v.lower() for v in headers.get_all("Upgrade"))
        has_token, _ = self._token_in(request, port)
        if len(origins) > 1:
            return "several Origin headers"
        if origins:
            o = urlsplit(origins[0]) if origins[0].startswith("http://") else None
            if o is None or _host_port(o.netloc) != host or o.path not in ("", "/"):
                return f"Origin {origins[0][:80]!r} is not this server's page"
        elif websocket and not has_token:
            return "a WebSocket without an Origin needs the token"
        if self.token_required and not has_token:
            return "the token is missing: open the URL usdrelight serve printed (with its ?token=...)"
        return ""

    async def check(self, connection, request, inner=None):
        """websockets' ``process_request``: a 403 response, or ``inner``'s (viser's) answer."""
        port = connection.local_address[1]
        reason = self.refusal(request, port)
        if reason:
            self.refusals += 1
            if time.monotonic() - self._logged >= LOG_EVERY:
                self._logged = time.monotonic()
                log.warning("refused a request (%d so far): %s", self.refusals, reason)
            return connection.respond(http.HTTPStatus.FORBIDDEN, f"Forbidden: {reason}\n")
        response = inner(connection, request) if inner is not None else None
        if inspect.isawaitable(response):
            response = await response
        if response is not None and self._token_in(request, port)[1]:
            response.headers["Set-Cookie"] = (f"{self.cookie_name(port)}={self.token}; Path=/; HttpOnly; "
                                              f"SameSite=Strict")
        return response


class _Start(msgspec.Struct):
    source_component_uuid: str
    transfer_uuid: str
    filename: str
    part_count: int
    size_bytes: int


class _Part(msgspec.Struct):
    source_component_uuid: str
    transfer_uuid: str
    part_index: int
    content: bytes


class _Update(msgspec.Struct):
    updates: dict


@functools.cache
def _message_types() -> frozenset:
    """The ``type`` names of viser's messages (what its decoder can look up)."""
    from viser.infra import Message

    return frozenset(m.__name__ for m in Message.get_subclasses())  # viser's decoder keys them by class name


def screen(gate: UploadGate, owner, data) -> str:
    """PASS, DROP or CLOSE for one incoming message. Uploads go through ``gate``; a widget change may change
    only its ``value`` (viser 1.1 would set any other name it carries as an attribute of the widget's server
    state: its callbacks, its id); everything else is viser's to judge."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        return CLOSE  # a text frame: viser's page speaks binary msgpack only (viser asserted, a traceback each)
    if len(data) > MAX_FRAME_BYTES:
        log.warning("a %d-byte message was refused (at most %d)", len(data), MAX_FRAME_BYTES)
        return CLOSE
    try:  # decoded once here: too deep a message would make viser's own decoder raise
        message = msgspec.msgpack.decode(data)
    except RecursionError:
        log.warning("a message nested too deeply was refused")
        return CLOSE
    except msgspec.DecodeError:
        return CLOSE  # not msgpack: viser's decoder raised, a traceback each
    kind = message.get("type") if isinstance(message, dict) else None
    if kind not in _message_types():
        return DROP  # viser looked the type up and raised KeyError (AttributeError for a non-dict)
    try:
        if kind == UPLOAD_START:
            m = msgspec.convert(message, _Start)
            return gate.start(owner, m.transfer_uuid, m.filename, m.size_bytes, m.part_count,
                              m.source_component_uuid)
        if kind == UPLOAD_PART:
            m = msgspec.convert(message, _Part)
            return gate.part(owner, m.transfer_uuid, m.part_index, m.content, m.source_component_uuid)
        if kind == GUI_UPDATE:
            keys = set(msgspec.convert(message, _Update).updates)
            if keys - {"value"}:
                log.warning("a widget change that sets %s was dropped", ", ".join(sorted(map(str, keys))))
                return DROP
    except msgspec.ValidationError:
        return DROP
    return PASS


def _connection_class(gate: UploadGate):
    def evict(owner) -> None:  # a stalled transfer's connection: closing it makes viser drop its parts
        asyncio.get_running_loop().create_task(owner.close(1008, "upload stalled"))

    gate.on_evict = evict

    class GuardedConnection(ws_server.ServerConnection):
        """A viser connection whose incoming upload messages pass the gate first."""

        async def recv(self, decode=None):
            while True:
                data = await super().recv(decode)
                verdict = screen(gate, self, data)
                if verdict == PASS:
                    return data
                if verdict == CLOSE:
                    await self.close(1008, "message refused")

        def connection_lost(self, exc):
            gate.disconnected(self)
            super().connection_lost(exc)

    return GuardedConnection


def _quiet_handshakes(record: logging.LogRecord) -> bool:
    """websockets logs a traceback for each connection that closes without a valid request (any client can
    make one): dropped, as viser drops them once its first page is served."""
    return record.getMessage() != "opening handshake failed"


@contextlib.contextmanager
def guarded(guard: Guard):
    """Build a ViserServer inside this block: its server then applies ``guard`` (see the module docstring).
    Raises UsdRelightError at the end of the block if no server was built through it."""
    real = ws_server.serve
    connection_class = _connection_class(guard.gate or UploadGate())

    class GuardedServe(real):
        def __init__(self, handler, *args, process_request=None, create_connection=None, **kwargs):
            async def check(connection, request):
                return await guard.check(connection, request, process_request)

            # a viser that brings its own connection class keeps it, unscreened: guard.installed stays False
            # and guarded() raises (the app then stops this server); Host/Origin are checked meanwhile
            super().__init__(handler, *args, process_request=check,
                             create_connection=create_connection or connection_class, **kwargs)
            guard.installed = create_connection is None

    logging.getLogger("websockets.server").addFilter(_quiet_handshakes)
    with _install_lock:
        ws_server.serve = GuardedServe
        try:
            yield guard
        finally:
            ws_server.serve = real
    if not guard.installed:
        raise UsdRelightError("this viser version does not build its server with websockets.asyncio.server.serve "
                              "as usdrelight serve expects: it cannot guard it and refuses to serve")
