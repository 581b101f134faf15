"""Real federation between processes on Flower (``flwr``): one SuperNode per rover.

A thin adapter, laid out like Flower's own quickstart apps:

``client_app``  the rover's ``ClientApp`` (imports ``flwr``)
``server_app``  the base station's ``ServerApp`` and its strategy (imports ``flwr``)
``records``     fedmap payload bytes inside Flower records (imports ``flwr``)
``task``        what the apps do, Flower-free: rover rounds, ground truth, checkpoints, outputs
``settings``    Flower's run / node config -> fedmap settings, through :mod:`fedmap.config`
``launch``      starting the SuperLink and ``flwr run`` for ``fedmap base-station``; processes, certificates
``rover``       ``fedmap rover``: its SuperNode, kept connected across link faults, every wait bounded
``warm``        one process per rover that imports torch once and forks each message's ClientApp
``checkpoint``  the base station's atomic, checked checkpoints (``--resume``)
``faults``      faults a rover can inject into its uplink, for fault-injection tests

The math is the code the in-process runner uses (:func:`fedmap.federation.runner.rover_step`
and :func:`~fedmap.federation.runner.base_step`); what crosses the link is fedmap's own
payload bytes (:mod:`fedmap.federation.codecs`) carried as a ``uint8`` array in an
``ArrayRecord``. Flower is an optional extra (``pip install 'fedmap[flower]'``): only
``client_app``, ``server_app`` and ``records`` import it (an import-linter contract).
"""

from __future__ import annotations

import importlib.util

from fedmap.errors import FedmapError

INSTALL_HINT = "Flower is not installed; run: pip install 'fedmap[flower]'"
#: Environment variable of fedmap's SuperNode (:mod:`fedmap.flower.supernode`): seconds between
#: its polls of its SuperLink when it has no message (Flower's own: 3 s); ``fedmap rover --poll``.
POLL_ENV = "FEDMAP_SUPERNODE_POLL"
#: Environment variable of fedmap's SuperNode: seconds between its heartbeats (Flower's own: 30 s;
#: ``fedmap rover --heartbeat``). The SuperLink takes a SuperNode for gone after two missed ones.
HEARTBEAT_ENV = "FEDMAP_SUPERNODE_HEARTBEAT"
#: The heartbeat intervals Flower 1.41's SuperLink accepts (``flwr.common.constant``), in seconds.
HEARTBEAT_RANGE = (10.0, 1800.0)
#: Environment variables of fedmap's SuperNode: the TLS client certificate it presents to the base's
#: front, and its private key, both PEM files (``fedmap rover`` sets them from ``--auth-key``).
CLIENT_CERT_ENV, CLIENT_KEY_ENV = "FEDMAP_SUPERNODE_CLIENT_CERT", "FEDMAP_SUPERNODE_CLIENT_KEY"
#: Environment variable naming the file that holds a base station's control secret, set by the
#: launcher for its own Control API calls (:mod:`fedmap.flower.control`).
CONTROL_SECRET_ENV = "FEDMAP_CONTROL_SECRET_FILE"
#: Flower's SuperExec: seconds between its polls for a task (a ClientApp to start; Flower's own: 1 s).
SUPEREXEC_POLL_ENV = "FLWR_SUPEREXEC_TASK_POLL_INTERVAL"


def require_flwr() -> None:
    """Raise a one-line :class:`FedmapError` when ``flwr`` cannot be imported."""
    try:
        found = importlib.util.find_spec("flwr") is not None
    except ValueError:  # sys.modules["flwr"] is None: the import is blocked
        found = False
    if not found:
        raise FedmapError(INSTALL_HINT)
