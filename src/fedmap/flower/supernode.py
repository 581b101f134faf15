"""Flower's ``flower-supernode``, with one fix for links that drop: ``python -m fedmap.flower.supernode ARGS``.

Flower 1.41's SuperNode retries a failed call to its SuperLink with exponential backoff for
up to ``--max-wait-time`` seconds, except when the error's text mentions ``ssl``, ``tls`` or
``certificate``: that it takes for a certificate problem and gives up at once. A link that
drops during a TLS handshake raises ``[SSL: UNEXPECTED_EOF_WHILE_READING] EOF occurred in
violation of protocol``, so one short cut ended every SuperNode that was reconnecting, and
with SuperNode authentication the SuperLink refuses a new SuperNode for the same key until
the old one's heartbeat has lapsed (2 x 30 s): the rover missed the round.

Here the connection's retry policy treats an EOF in the handshake as the transport error it
is (retried, within ``--max-wait-time``); a certificate that does not verify still ends the
SuperNode at once.

Its heartbeat interval can be set (``FEDMAP_SUPERNODE_HEARTBEAT``, ``fedmap rover
--heartbeat``): Flower 1.41 fixes it at 30 s, and its SuperLink takes a SuperNode for gone
only after two intervals without one. Until then a message to a rover that died waits, and
the rover's key, restarted, is refused as still in use. Everything else is Flower's own
``flower-supernode``.
"""

from __future__ import annotations

import os
import sys
import time

import flwr.supercore.heartbeat as heartbeat
import flwr.supernode.fleet_http_connection as fleet
from flwr.supercore.retry import RetryInvoker, make_simple_http_retry_invoker
from flwr.supernode.cli import flower_supernode

from fedmap.flower import CLIENT_CERT_ENV, CLIENT_KEY_ENV, HEARTBEAT_ENV, POLL_ENV
from fedmap.flower.polling import quick_pulls

#: Substrings of an SSL error raised by a link that went away mid-handshake (not a TLS problem).
LINK_DROPPED = ("unexpected_eof_while_reading", "eof occurred in violation of protocol")


def link_dropped(exc: BaseException) -> bool:
    """Whether ``exc`` is a TLS handshake cut short by the link, not a certificate problem."""
    text = str(exc).lower()
    return any(s in text for s in LINK_DROPPED) and "certificate" not in text


def retry_invoker() -> RetryInvoker:
    """Flower's HTTP retry invoker, but an EOF during a TLS handshake is retried."""
    invoker = make_simple_http_retry_invoker()
    flower_says = invoker.should_giveup

    def should_giveup(exc: Exception) -> bool:
        if link_dropped(exc):
            return False
        return flower_says(exc) if flower_says is not None else False

    invoker.should_giveup = should_giveup
    return invoker


class _Polling:
    """Flower's ``time`` module for its SuperNode loop, with every wait capped at ``poll`` s."""

    def __init__(self, poll: float) -> None:
        self.poll = poll

    def sleep(self, seconds: float) -> None:
        time.sleep(min(seconds, self.poll))

    def __getattr__(self, name: str):
        return getattr(time, name)


def set_heartbeat(seconds: float) -> None:
    """Make this process's SuperNode announce, and keep, a heartbeat every ``seconds``: the
    interval it activates with and sends with each heartbeat (the SuperLink's patience is twice
    it), and the one its sender waits by (Flower's: the interval less the call's 5 s timeout,
    times 0.7-0.9)."""
    for module in (fleet, heartbeat):
        assert hasattr(module, "HEARTBEAT_DEFAULT_INTERVAL"), f"Flower's {module.__name__} changed"
        module.HEARTBEAT_DEFAULT_INTERVAL = seconds  # type: ignore[attr-defined]


def present_certificate(cert: str, key: str) -> None:
    """Every HTTPS client this process makes from now on presents ``cert`` (PEM) with its
    private key ``key`` (PEM): the base station's front admits only clients with a
    certificate of its CA (:mod:`fedmap.flower.gate`), and Flower 1.41's SuperNode has no
    option for one. Its verification of the server (``--root-certificates``) is unchanged."""
    import ssl

    import httpx

    base = httpx.Client

    class Client(base):  # type: ignore[misc, valid-type]
        def __init__(self, *args, verify=True, **kwargs) -> None:
            if verify is not False:
                ctx = verify if isinstance(verify, ssl.SSLContext) else ssl.create_default_context(
                    cafile=verify if isinstance(verify, str) else None)
                ctx.load_cert_chain(cert, key)
                verify = ctx
            super().__init__(*args, verify=verify, **kwargs)

    httpx.Client = Client  # type: ignore[misc]


def main(argv: list[str]) -> int:
    fleet.make_simple_http_retry_invoker = retry_invoker  # the SuperNode's connection to its SuperLink
    if os.environ.get(CLIENT_CERT_ENV):  # the rover's TLS client certificate (fedmap rover --auth-key K: K.crt)
        present_certificate(os.environ[CLIENT_CERT_ENV], os.environ[CLIENT_KEY_ENV])
    beat = os.environ.get(HEARTBEAT_ENV)
    if beat:
        set_heartbeat(float(beat))
    poll = os.environ.get(POLL_ENV)
    if poll:
        import flwr.supernode.start_client_internal as loop

        loop.time = _Polling(float(poll))  # type: ignore[assignment]
        quick_pulls()
    sys.argv = ["flower-supernode", *argv]
    flower_supernode()
    return 0


if __name__ == "__main__":  # pragma: no cover - a process of its own
    sys.exit(main(sys.argv[1:]))
