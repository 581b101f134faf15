"""The round trip of a Zenoh query between two processes on loopback: what the transport
itself adds to a round of a mission over Zenoh (a round's orders are queries, its reports
their replies).

    python benchmarks/zenoh_rtt.py [--queries 200] [--size 1000]

A child process declares a queryable that answers with the query's payload; this process
asks it ``--queries`` times with ``--size`` bytes and prints the median and 95th percentile.
Plain TCP and mutual TLS (a throw-away CA, as ``--deploy zenoh`` makes).
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from fedmap.flower.launch import free_port, make_certs
from fedmap.zenohnet.session import Certs, node_config, open_session

ECHO = """
import sys
from pathlib import Path
from fedmap.zenohnet.session import Certs, node_config, open_session
ep, certs = sys.argv[1], sys.argv[2]
tls = Certs.for_node(Path(certs), "rover0") if certs else None
s = open_session(node_config(connect=[ep], certs=tls))
q = s.declare_queryable("rtt/echo")
print("ready", flush=True)
for query in q:
    data = query.payload.to_bytes() if query.payload is not None else b""
    query.reply(query.key_expr, data)
    query.drop()
    if data == b"stop":
        break
"""


def probe(queries: int, size: int, tls: bool) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        certs = Path(tmp) / "certs"
        if tls:
            make_certs(certs, hosts=["127.0.0.1"], rovers=1, keep_ca_key=False)
        ep = f"{'tls' if tls else 'tcp'}/127.0.0.1:{free_port()}"
        with open_session(node_config(listen=[ep], certs=Certs.for_node(certs, "base") if tls else None)) as s:
            child = subprocess.Popen([sys.executable, "-c", ECHO, ep, str(certs) if tls else ""],
                                     stdout=subprocess.PIPE, text=True)
            assert child.stdout is not None and child.stdout.readline().strip() == "ready"
            payload, times = b"x" * size, []
            while not [r for r in s.get("rtt/echo", payload=payload, timeout=5.0) if r.ok is not None]:
                time.sleep(0.05)  # (until the queryable is known)
            for _ in range(queries):
                t0 = time.perf_counter()
                replies = [r for r in s.get("rtt/echo", payload=payload, timeout=5.0) if r.ok is not None]
                times.append(time.perf_counter() - t0)
                assert replies and replies[0].ok.payload.to_bytes() == payload
            list(s.get("rtt/echo", payload=b"stop", timeout=5.0))
            child.wait(timeout=30)
    times.sort()
    return {"tls": tls, "queries": queries, "bytes": size, "median_ms": round(statistics.median(times) * 1e3, 3),
            "p95_ms": round(times[int(0.95 * (len(times) - 1))] * 1e3, 3)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--queries", type=int, default=200)
    ap.add_argument("--size", type=int, default=1000)
    a = ap.parse_args()
    for tls in (False, True):
        print(json.dumps(probe(a.queries, a.size, tls)))


if __name__ == "__main__":
    main()
