"""A node's Zenoh session: where it listens and connects, its TLS and access control, and
the team's key expressions.

Keys (``<team>`` names one mission's team, so teams can share a network):

* ``fedmap/<team>/rover/<k>/order``: rover ``k``'s queryable; the base's query carries an
  order (:class:`~fedmap.mission.network.remote.Order`), the reply is its report. The
  query's attachment carries a rebuild history to a rover that lost its state.
* ``fedmap/<team>/rover/<k>/done``: the mission is over (the rover may stop).
* ``fedmap/<team>/base/mission``: the base's queryable; a rover asks it for the mission (the
  resolved TOML) whose id an order names.
* ``fedmap/<team>/alive/rover/<k>`` and ``fedmap/<team>/alive/base``: liveliness tokens,
  present while the node runs (the base waits for every rover's; a rover that vanishes mid-order
  is noticed at once, not at the query's timeout).

Security: with a certificate folder (``fedmap certs``) every link is TLS with mutual
authentication (the base listens with ``server.pem``, each rover connects with
``rover<k>.crt`` and ``rover<k>.key``, both checked against ``ca.crt``), and the base's
access-control rules (:func:`acl`) let rover ``k``, known by its certificate's common name,
answer and declare only under its own keys. Listening beyond this machine without them is
refused unless ``insecure`` (:func:`~fedmap.flower.launch.check_exposure`).
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from fedmap.errors import FedmapError
from fedmap.flower.launch import is_loopback

#: The default port a base station listens on (Zenoh's own default is 7447).
DEFAULT_PORT = 7447
#: A team's name: the chunk of its keys (no key-expression wildcards or separators).
_TEAM = re.compile(r"[A-Za-z0-9_.-]{1,64}")


def check_team(team: str) -> str:
    if not _TEAM.fullmatch(team):
        raise FedmapError(f"team name {team!r}: use 1-64 letters, digits, '_', '.' or '-'")
    return team


def order_key(team: str, k: int | str) -> str:
    return f"fedmap/{team}/rover/{k}/order"


def done_key(team: str, k: int | str) -> str:
    return f"fedmap/{team}/rover/{k}/done"


def mission_key(team: str) -> str:
    return f"fedmap/{team}/base/mission"


def alive_key(team: str, who: str) -> str:
    """``who``: ``base`` or ``rover/<k>``."""
    return f"fedmap/{team}/alive/{who}"


def endpoint(address: str, *, tls: bool) -> str:
    """A Zenoh endpoint from ``HOST:PORT`` (or an endpoint already, ``tcp/...``, ``tls/...``)."""
    if "/" in address:
        proto = address.split("/", 1)[0]
        if proto not in ("tcp", "tls", "udp", "quic"):
            raise FedmapError(f"endpoint {address!r}: use HOST:PORT or tcp/HOST:PORT (tls/... with --certs)")
        if tls and proto != "tls":
            raise FedmapError(f"endpoint {address!r} is not TLS, and --certs asks for TLS: use tls/HOST:PORT or HOST:PORT")
        return address
    host, sep, port = address.rpartition(":")
    if not sep or not port.isdigit() or not 0 <= int(port) <= 65535 or not host:
        raise FedmapError(f"address {address!r}: use HOST:PORT, e.g. 127.0.0.1:{DEFAULT_PORT}")
    return f"{'tls' if tls else 'tcp'}/{host}:{port}"


def host_of(ep: str) -> str:
    return ep.split("/", 1)[1].rpartition(":")[0].strip("[]")


@dataclass(frozen=True)
class Certs:
    """A node's TLS files: the CA every peer is checked against, and its own certificate and key."""

    ca: Path
    cert: Path
    key: Path

    @classmethod
    def for_node(cls, folder: Path, who: str) -> Certs:
        """``who``: ``base`` (``server.pem``, ``server.key``) or ``rover<k>`` (``rover<k>.crt``, ``rover<k>.key``)."""
        folder = Path(folder)
        cert, key = (("server.pem", "server.key") if who == "base" else (f"{who}.crt", f"{who}.key"))
        files = [folder / n for n in ("ca.crt", cert, key)]
        missing = [p.name for p in files if not p.is_file()]
        if missing:
            raise FedmapError(f"{folder} lacks {', '.join(missing)} for {who}: make them with `fedmap certs {folder} "
                              "--host BASE_HOST --rovers N`")
        return cls(*files)


def acl(team: str, rovers: int) -> dict:
    """The base's (or lander's) access-control rules: everything is denied but what each
    node needs. The base (no client certificate: it listens) is trusted through its own
    session. Rover ``k`` (common name ``rover<k>``) may declare and answer its own queryable
    and hold its own liveliness token (it sees everyone's), ask the base for the mission, and
    on a peer mission post mail as itself only (``fedmap/<team>/peer/*/mail/*/<k>``), take
    its own (``fedmap/<team>/peer/<k>/mail/**``), post its cell and say it finished as
    itself only, and ask for the plan."""
    rules: list[dict] = [{
        "id": "desk", "permission": "allow", "flows": ["egress", "ingress"],
        "messages": ["query", "reply", "declare_queryable"],
        "key_exprs": [mission_key(team), f"fedmap/{team}/base/plan"],
    }, {
        "id": "see-alive", "permission": "allow", "flows": ["egress", "ingress"],
        "messages": ["liveliness_query", "declare_liveliness_subscriber"], "key_exprs": [alive_key(team, "**")],
    }, {
        "id": "told-alive", "permission": "allow", "flows": ["egress"],  # everyone's tokens reach it
        "messages": ["liveliness_token"], "key_exprs": [alive_key(team, "**")],
    }]
    subjects, policies = [], []
    for k in range(rovers):
        rules.append({"id": f"rover{k}", "permission": "allow", "flows": ["egress", "ingress"],
                      "messages": ["query", "reply", "declare_queryable", "liveliness_token"],
                      "key_exprs": [f"fedmap/{team}/rover/{k}/**", alive_key(team, f"rover/{k}"),
                                    alive_key(team, f"peer/{k}"), f"fedmap/{team}/peer/{k}/mail/**",
                                    f"fedmap/{team}/peer/*/mail/*/{k}", f"fedmap/{team}/base/table/*/{k}",
                                    f"fedmap/{team}/base/finished/{k}"]})
        subjects.append({"id": f"rover{k}", "cert_common_names": [f"rover{k}"]})
        policies.append({"rules": [f"rover{k}", "desk", "see-alive", "told-alive"], "subjects": [f"rover{k}"]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}


def node_config(*, listen: list[str] = (), connect: list[str] = (), certs: Certs | None = None,  # type: ignore[assignment]
                access: dict | None = None, mode: str = "peer", connect_timeout: float | None = None) -> Any:
    """A ``zenoh.Config`` for one node: ``listen`` and ``connect`` endpoints, no multicast
    scouting (a team finds its base by address; gossip still finds the rest; ``connect_timeout``:
    seconds a client waits for it to answer, None: for ever), ``certs`` for TLS
    with mutual authentication, ``access`` control rules (:func:`acl`) for the base."""
    import zenoh

    conf = zenoh.Config()

    def put(key: str, value: Any) -> None:
        conf.insert_json5(key, json.dumps(value))

    put("mode", mode)
    put("scouting/multicast/enabled", False)
    # a node listens only where told: a Zenoh peer's default (every interface, a random port,
    # plain TCP) would let anyone who reaches it past the TLS and access control of the base
    put("listen/endpoints", list(listen))
    # every byte goes over the link: Zenoh would hand a message above 3 kB to a process of this
    # machine through shared memory, around the network (and a thin link's limits)
    put("transport/shared_memory/enabled", False)
    if connect:
        put("connect/endpoints", list(connect))
        # keep trying: the base may start after its rovers (a client waits for it in zenoh.open:
        # up to ``connect_timeout`` s, then one line)
        put("connect/timeout_ms", -1 if connect_timeout is None else round(connect_timeout * 1000))
    if certs is not None:
        put("transport/link/tls", {
            "root_ca_certificate": str(certs.ca),
            "listen_private_key": str(certs.key), "listen_certificate": str(certs.cert),
            "connect_private_key": str(certs.key), "connect_certificate": str(certs.cert),
            "enable_mtls": True, "verify_name_on_connect": True,
        })
    if access is not None:
        put("access_control", access)
    return conf


def check_listen(endpoints: list[str], *, secure: bool, insecure: bool) -> None:
    """Refuse to listen beyond this machine without TLS and access control (any host that
    reaches the port could answer as a rover), unless ``insecure``."""
    for ep in endpoints:
        if not (secure or insecure or is_loopback(host_of(ep))):
            raise FedmapError(f"refusing to listen on {ep} without TLS and access control: any host that reaches it "
                              "could answer as a rover; make certificates with `fedmap certs DIR --host BASE_HOST "
                              "--rovers N` and pass --certs DIR, listen on 127.0.0.1, or pass --insecure on a "
                              "network you trust")


def open_session(conf: Any) -> Any:
    """``zenoh.open(conf)``; one line when it cannot (an endpoint in use, a bad certificate)."""
    import zenoh

    try:
        return zenoh.open(conf)
    except zenoh.ZError as e:
        line = str(e).splitlines()[0] if str(e) else type(e).__name__
        line = re.sub(r"\s+at \S+\.rs:\d+\.?$", "", line)  # (not the Rust source line it came from)
        raise FedmapError(f"zenoh: {line}") from None


__all__ = ["DEFAULT_PORT", "Certs", "acl", "alive_key", "check_listen", "check_team", "done_key", "endpoint",
           "host_of", "mission_key", "node_config", "open_session", "order_key"]
