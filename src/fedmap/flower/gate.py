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
- **a rover's relay** (:func:`serve_relay`, ``python -m fedmap.flower.gate relay ...``) is what
  presents that certificate: Flower's SuperNode cannot, so it speaks to a relay on its own
  machine's loopback, which carries its bytes to the front over mutual TLS.

Request bodies through the front are bounded (:data:`MAX_BODY`). The front is uvicorn (the
ASGI server Flower's SuperLink runs on); nothing here imports ``flwr``.
"""

from __future__ import annotations

import argparse
import asyncio
import hmac
import os
import ssl
import sys
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
#: The largest request or response body the front carries, in bytes. Flower splits what it
#: sends into objects (a message's arrays, chunked); the paper's network, the largest fedmap
#: sends, is 0.8 MB in all.
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
                raise ValueError(f"a request body over {self.max_body} bytes")
            return event
        try:
            await self.app(scope, bounded, send)
        except ValueError as e:
            if "request body over" not in str(e):
                raise
            await _answer(send, 413, f"fedmap: {e}")


def front_tls(certs: Path) -> dict:
    """uvicorn's TLS options for a front with mutual TLS: the base's server certificate, and
    clients must present one signed by ``certs/ca.crt``."""
    certs = Path(certs)
    return {"ssl_certfile": str(certs / "server.pem"), "ssl_keyfile": str(certs / "server.key"),
            "ssl_ca_certs": str(certs / "ca.crt"), "ssl_cert_reqs": ssl.CERT_REQUIRED}


def client_context(root_cert: Path, cert: Path, key_pem: Path) -> ssl.SSLContext:
    """A rover's TLS to the front: the base's CA, and the rover's certificate and key."""
    ctx = ssl.create_default_context(cafile=str(root_cert))
    ctx.load_cert_chain(str(cert), str(key_pem))
    return ctx


async def _pipe(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
    try:
        while chunk := await reader.read(1 << 16):
            writer.write(chunk)
            await writer.drain()
    except (ConnectionError, ssl.SSLError, OSError):
        pass
    finally:
        try:
            writer.close()
        except (ConnectionError, OSError):
            pass


async def relay(*, listen_port: int, target: str, ctx: ssl.SSLContext, local: ssl.SSLContext | None = None,
                ready: Callable[[], None] | None = None) -> None:
    """Accept on 127.0.0.1:``listen_port`` (TLS with ``local``, a server context: Flower's
    SuperNode authenticates only over TLS) and carry each connection's bytes to ``target``
    (``HOST:PORT``) over TLS with ``ctx``; a connection the far end refuses is closed."""
    host, _, port = target.rpartition(":")
    host = host.strip("[]")

    async def one(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            up_r, up_w = await asyncio.wait_for(asyncio.open_connection(host, int(port), ssl=ctx, server_hostname=host),
                                                30.0)
        except (TimeoutError, OSError, ssl.SSLError) as e:
            print(f"relay: {target}: {e}", file=sys.stderr, flush=True)
            writer.close()
            return
        await asyncio.gather(_pipe(reader, up_w), _pipe(up_r, writer))

    server = await asyncio.start_server(one, "127.0.0.1", listen_port, ssl=local)
    if ready is not None:
        ready()
    async with server:
        await server.serve_forever()


def serve_relay(*, listen_port: int, target: str, root_cert: Path, cert: Path, key_pem: Path,
                local_cert: Path | None = None, local_key: Path | None = None) -> None:
    local = None
    if local_cert is not None:
        local = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
        local.load_cert_chain(str(local_cert), str(local_key) if local_key else None)
    asyncio.run(relay(listen_port=listen_port, target=target, ctx=client_context(root_cert, cert, key_pem),
                      local=local))


def local_certificate(folder: Path) -> tuple[Path, Path]:
    """A throw-away self-signed certificate for 127.0.0.1 and ``localhost`` and its key (readable
    by its owner only) in ``folder``: what the relay shows the SuperNode on its own machine."""
    import datetime as dt
    import ipaddress

    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "fedmap rover relay")])
    now = dt.datetime.now(dt.UTC)
    cert = (x509.CertificateBuilder().subject_name(name).issuer_name(name).public_key(key.public_key())
            .serial_number(x509.random_serial_number()).not_valid_before(now - dt.timedelta(minutes=5))
            .not_valid_after(now + dt.timedelta(days=3650))
            .add_extension(x509.SubjectAlternativeName([x509.IPAddress(ipaddress.ip_address("127.0.0.1")),
                                                        x509.DNSName("localhost")]), critical=False)
            .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
            .sign(key, hashes.SHA256()))
    crt, pem = Path(folder) / "relay.crt", Path(folder) / "relay.key"
    crt.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    fd = os.open(pem, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "wb") as fh:
        fh.write(key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                   serialization.NoEncryption()))
    return crt, pem


def main(argv: list[str] | None = None) -> int:  # pragma: no cover - a process of its own
    p = argparse.ArgumentParser(prog="python -m fedmap.flower.gate")
    sub = p.add_subparsers(dest="what", required=True)
    r = sub.add_parser("relay")
    r.add_argument("--port", type=int, required=True)
    r.add_argument("--target", required=True)
    r.add_argument("--root-cert", type=Path, required=True)
    r.add_argument("--cert", type=Path, required=True)
    r.add_argument("--key", type=Path, required=True)
    r.add_argument("--local-cert", type=Path)
    r.add_argument("--local-key", type=Path)
    a = p.parse_args(argv)
    try:
        if a.what == "relay":
            serve_relay(listen_port=a.port, target=a.target, root_cert=a.root_cert, cert=a.cert, key_pem=a.key,
                        local_cert=a.local_cert, local_key=a.local_key)
    except KeyboardInterrupt:
        pass
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
