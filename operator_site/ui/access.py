"""Who may control the robot from the page.

On loopback without a token every client of the page may (the machine's users are trusted). A
page that listens beyond loopback, or was given a token, admits a client only once it has shown
the token: in its websocket's URL (the page's URL :func:`page_url` prints, which makes the
browser connect to ``ws://HOST:PORT/?token=…``) or typed into the page. Until then the client
sees the page but nothing it sends reaches the page's callbacks: its messages are dropped before
viser dispatches them, so it cannot press a button, change an input, click or drag in the 3D
view. No client may open viser's share tunnel, which would put the page on the internet.
"""

from __future__ import annotations

import inspect
import ipaddress
import logging
import re
import secrets
import threading
from urllib.parse import parse_qs, urlsplit

import viser
from viser import _messages

log = logging.getLogger("operator-site")

LOOPBACK_NAMES = ("localhost",)
TOKEN_PARAM = "token"
TOKEN_PATTERN = re.compile(r"[A-Za-z0-9_~.-]{16,}")
"""A token a deployment sets itself: long enough not to be guessed, and characters that pass
through the page's URL unchanged."""
READ_ONLY_MESSAGES = (
    _messages.ViewerCameraMessage,
    _messages.GetRenderResponseMessage,
    _messages.LocalStorageGetItemResponseMessage,
)
"""What a client without the token may still send: its own view of the scene."""
NEVER_MESSAGES = (_messages.ShareUrlRequest, _messages.ShareUrlDisconnect)
"""What no client may send: a share tunnel would publish the page beyond this machine."""


def is_loopback_host(host: str) -> bool:
    """Whether the page listening on ``host`` is reachable from this machine only."""
    if host.lower() in LOOPBACK_NAMES:
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def new_token() -> str:
    """A fresh access token, URL-safe."""
    return secrets.token_urlsafe(24)


def check_token(token: str) -> str:
    """``token`` if it may be the page's access token, else ValueError saying why."""
    if not TOKEN_PATTERN.fullmatch(token):
        raise ValueError(
            "the access token must be at least 16 characters of A-Z, a-z, 0-9, '_', '-', '.', "
            "'~' (omit it for a new random one)"
        )
    return token


VIEW_DPR_RANGE = (0.25, 4.0)
"""Device-pixel ratios the 3D view may be fixed at. At a quarter the blocks still show but the
names drawn on them no longer read (0.5 keeps them legible); 4 is the densest displays'."""


def check_view_dpr(ratio: float) -> float:
    """``ratio`` if the 3D view may be drawn at it, else ValueError naming the range."""
    if not VIEW_DPR_RANGE[0] <= ratio <= VIEW_DPR_RANGE[1]:
        raise ValueError(
            f"the 3D view's device-pixel ratio must be in {VIEW_DPR_RANGE[0]:g}.."
            f"{VIEW_DPR_RANGE[1]:g}, got {ratio:g}"
        )
    return ratio


def page_url(
    host: str,
    port: int,
    token: str | None,
    browse_host: str | None = None,
    view_dpr: float | None = None,
) -> str:
    """The URL to open: with a token, one whose websocket carries it (viser's page connects to
    the ``websocket`` parameter's address, query included). ``browse_host`` replaces a wildcard
    ``host`` (0.0.0.0, ::) with a name other machines can reach. ``view_dpr`` fixes the 3D
    view's device-pixel ratio (viser's ``fixedDpr``; None: the browser's own, which viser lowers
    to 0.75× while frames are slow)."""
    name = browse_host or host
    if ":" in name and not name.startswith("["):
        name = f"[{name}]"
    base = f"http://{name}:{port}/"
    params = []
    if view_dpr is not None:
        params.append(f"fixedDpr={check_view_dpr(view_dpr):g}")
    if token is not None:  # last: the websocket's address carries a query of its own
        params.append(f"websocket=ws://{name}:{port}/?{TOKEN_PARAM}={check_token(token)}")
    return base + ("?" + "&".join(params) if params else "")


class PageAccess:
    """The token (None: every client may control) and the clients that showed it."""

    def __init__(self, token: str | None) -> None:
        self.token = None if token is None else check_token(token)
        self._admitted: set[int] = set()
        self._lock = threading.Lock()

    @property
    def open(self) -> bool:
        return self.token is None

    def admit(self, client_id: int, token: str | None) -> bool:
        """Admit ``client_id`` if ``token`` is the page's; whether it is admitted now."""
        if self.open:
            return True
        ok = token is not None and secrets.compare_digest(token.encode(), self.token.encode())
        if ok:
            with self._lock:
                self._admitted.add(client_id)
        return ok or self.allows(client_id)

    def allows(self, client_id: int) -> bool:
        """Whether ``client_id`` may control the robot."""
        if self.open:
            return True
        with self._lock:
            return client_id in self._admitted

    def forget(self, client_id: int) -> None:
        with self._lock:
            self._admitted.discard(client_id)


def connection_token(server: viser.ViserServer, client_id: int) -> str | None:
    """The token in ``client_id``'s websocket URL, if any."""
    connection = server._websock_server._live_connections.get(client_id)
    if connection is None or connection.request is None:
        return None
    values = parse_qs(urlsplit(connection.request.path).query).get(TOKEN_PARAM)
    return values[0] if values else None


def install_gate(server: viser.ViserServer, access: PageAccess) -> None:
    """Drop every message from a client that may not control before viser dispatches it.

    viser has no public hook for this (nor for a client's URL): this wraps its websocket
    server's dispatch, and refuses to start if viser's internals moved (fail closed)."""
    ws_server = server._websock_server
    dispatch = getattr(ws_server, "_handle_incoming_message", None)
    live = getattr(ws_server, "_live_connections", None)
    if not inspect.iscoroutinefunction(dispatch) or not isinstance(live, dict):
        raise RuntimeError(
            f"viser {viser.__version__} hides the websocket dispatch this page gates: "
            "cannot restrict control to clients with the token"
        )

    async def gated(client_id: int, message: _messages.Message) -> None:
        if isinstance(message, NEVER_MESSAGES):
            log.warning("client %d asked for a share tunnel: refused", client_id)
            return
        if not isinstance(message, READ_ONLY_MESSAGES) and not access.admit(
            client_id, connection_token(server, client_id)
        ):
            return  # a read-only client: the page says how to get access
        await dispatch(client_id, message)

    ws_server._handle_incoming_message = gated
