"""What stands between a base station's SuperLink and everyone else.

Flower 1.41 serves its Fleet API (the rovers'), its Control API (``flwr run``, ``flwr ls``,
``flwr stop``: whoever reaches it can make the base run an app of their choosing) and its
Runtime API on one HTTP port, and open-source Flower authenticates none of the Control API.
So fedmap never lets anyone reach that port but its own processes:

- **the SuperLink listens on loopback only** (:mod:`fedmap.flower.superlink`), and there its
  Control API answers only requests that carry the launcher's secret (:data:`CONTROL_HEADER`;
  :class:`ControlGuard`): other local users cannot submit or stop a run either. fedmap's own
  control calls go through :mod:`fedmap.flower.control`, which adds the header;
- **the front** is what listens where the rovers reach the base: the same SuperLink's app,
  served by the same process on a second address behind :class:`FleetOnly`, which lets
  through only the Fleet API's routes (:data:`FLEET_ROUTES`, POST) and answers everything
  else 404. With certificates it is TLS with *mutual* authentication: a client must present
  a certificate signed by the base's CA (``roverK.crt``, made by ``fedmap certs``) before any
  HTTP is read. (A separate front process that forwarded each request over loopback was
  tried first: 3-4 ms more per request, a mission's sync round 20-50 % longer);
- **a rover's SuperNode presents that certificate** (:func:`fedmap.flower.supernode.present_certificate`:
  Flower's has no option for one). A relay beside it that carried its bytes to the front
  over mutual TLS was tried first: one more process and hop per rover, for nothing.

Request bodies through the front are bounded (:data:`MAX_BODY`). The front is uvicorn (the
ASGI server Flower's SuperLink runs on); nothing here imports ``flwr``.
"""

from __future__ import annotations

import hmac
import ssl
from collections.abc import Awaitable, Callable
from pathlib import Path

#: The header that carries the launcher's secret to the SuperLink's Control API.
CONTROL_HEADER = "x-fedmap-control"
#: Routes the SuperLink serves without the secret (on loopback): the Fleet API (reached from
#: outside only through the front), the Runtime API (Flower's SuperExec and ServerApp, each
#: request checked by Flower against a task's token) and the health check.
OPEN_PREFIXES = ("/v1/fleet/", "/v1/runtime/")
OPEN_PATHS = ("/health",)
#: The Fleet API of Flower 1.41 (``flwr.superlink.routers.fleet.router``): all the front forwards.
FLEET_ROUTES = frozenset(f"/v1/fleet/{r}" for r in (
    "register-node", "activate-node", "deactivate-node", "unregister-node", "send-node-heartbeat", "pull-messages",
    "push-messages", "get-run", "get-fab", "push-object", "pull-object", "confirm-message-received"))
#: The largest request body the front lets through, in bytes. Flower splits what it sends
#: into objects (a message's arrays, chunked); the paper's network, the largest fedmap sends,
#: is 0.8 MB in all.
MAX_BODY = 64 << 20

Send = Callable[[dict], Awaitable[None]]
Receive = Callable[[], Awaitable[dict]]


async def _answer(send: Send, status: int, text: str) -> None:
    body = (text + "\n").encode()
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"text/plain"), (b"content-length", str(len(body)).encode())]})
    await send({"type": "http.response.body", "body": body})


class ControlGuard:
    """ASGI middleware: a request for anything but :data:`OPEN_PREFIXES` / :data:`OPEN_PATHS`
    (the Control API above all) is refused (403) unless it carries ``secret`` in
    :data:`CONTROL_HEADER` (compared in constant time)."""

    def __init__(self, app, secret: bytes) -> None:
        if len(secret) < 16:
            raise ValueError("the control secret must be at least 16 bytes")
        self.app, self.secret = app, secret

    async def __call__(self, scope: dict, receive: Receive, send: Send) -> None:
        if scope["type"] == "http" and not (scope["path"].startswith(OPEN_PREFIXES) or scope["path"] in OPEN_PATHS):
            given = next((v for k, v in scope["headers"] if k.lower() == CONTROL_HEADER.encode()), b"")
            if not hmac.compare_digest(given, self.secret):
                await _answer(send, 403, "fedmap: this SuperLink's Control API answers only the process that started it")
                return
        await self.app(scope, receive, send)


class _TooLarge(Exception):
    """A request body that goes on past :data:`MAX_BODY` without saying its length."""


class FleetOnly:
    """ASGI middleware for the front: POST to a :data:`FLEET_ROUTES` route goes to ``app``
    (its body at most :data:`MAX_BODY` bytes, announced or read: else 413); anything else is
    404 and never reaches it."""

    def __init__(self, app, max_body: int = MAX_BODY) -> None:
        self.app, self.max_body = app, max_body

    async def __call__(self, scope: dict, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            return  # no lifespan (the loopback listener runs the app's) and no websockets
        if scope["method"] != "POST" or scope["path"] not in FLEET_ROUTES:
            await _answer(send, 404, "fedmap: only the Fleet API is served here")
            return
        announced = next((v for k, v in scope["headers"] if k.lower() == b"content-length"), None)
        if announced is not None and (not announced.isdigit() or int(announced) > self.max_body):
            await _answer(send, 413, f"fedmap: a request body over {self.max_body} bytes")
            return
        scope = {**scope, "headers": [(k, v) for k, v in scope["headers"] if k.lower() != CONTROL_HEADER.encode()]}
        size = 0

        async def bounded() -> dict:
            nonlocal size
            event = await receive()
            size += len(event.get("body", b""))
            if size > self.max_body:  # a body that says nothing of its length and goes on
                raise _TooLarge
            return event
        try:
            await self.app(scope, bounded, send)
        except _TooLarge:
            await _answer(send, 413, f"fedmap: a request body over {self.max_body} bytes")


def front_tls(certs: Path) -> dict:
    """uvicorn's TLS options for a front with mutual TLS: the base's server certificate, and
    clients must present one signed by ``certs/ca.crt``."""
    certs = Path(certs)
    return {"ssl_certfile": str(certs / "server.pem"), "ssl_keyfile": str(certs / "server.key"),
            "ssl_ca_certs": str(certs / "ca.crt"), "ssl_cert_reqs": ssl.CERT_REQUIRED}
