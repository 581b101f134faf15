"""What crosses the link of a mission on processes, per rover per sync: the orders and
reports (fedmap's frames) against the strategy's own bytes the ledger counts.

    python benchmarks/link_bytes.py                       # the default mission, predictive and raw
    python benchmarks/link_bytes.py --strategies fedmap

Every rover runs behind bytes in this process (:func:`fedmap.mission.network.remote.loopback`, the
reference a mission on processes is checked against), so what is measured is exactly what a
transport carries, without Flower's own envelope. Prints, per strategy: the ledger's bytes
(uplinks and downlinks), the bytes of every order and report, their ratio, and the bytes
each rover writes to its own log (scoring, off the link). Writes
``benchmarks/results/link_bytes.json``.
"""

from __future__ import annotations

import argparse
import json
import platform
from pathlib import Path

from fedmap.mission import load_mission, mission_terrain
from fedmap.mission.network.remote import ProcessBase, loopback, rounds
from fedmap.mission.sim import prepare_mission

ROOT = Path(__file__).resolve().parent.parent


def measure(name: str, mission) -> dict:
    base, rovers = ProcessBase(mission, name), loopback(mission, name)
    sizes = {"orders": 0, "reports": 0, "messages": 0}

    def send(orders: dict[int, bytes]) -> dict[int, bytes]:
        reports = rovers(orders)
        sizes["orders"] += sum(map(len, orders.values()))
        sizes["reports"] += sum(map(len, reports.values()))
        sizes["messages"] += len(orders)
        return reports

    list(rounds(base, send))
    ledger = base.link.ledger
    counted = sum(m.bytes for m in ledger)
    logs = getattr(rovers, "logs", None)  # each rover's own log (absent before scoring left the link)
    logged = sum(len(e.to_bytes()) for log in logs for e in log) if logs is not None else 0
    wire = sizes["orders"] + sizes["reports"]
    return {"strategy": name, "counted_bytes": counted, "order_bytes": sizes["orders"],
            "report_bytes": sizes["reports"], "wire_bytes": wire, "wire_over_counted": wire / max(counted, 1),
            "messages": sizes["messages"], "framing_per_message": (wire - counted) / max(sizes["messages"], 1),
            "logged_bytes": logged}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--strategies", nargs="+", default=["predictive", "raw"])
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks/results/link_bytes.json")
    a = ap.parse_args()
    config, source, _ = load_mission(overrides=[{"mission": {"strategies": a.strategies}}])
    truth, elevation, prior, profiles = mission_terrain(config, source)
    m = prepare_mission(config, truth, elevation=elevation, prior=prior, profiles=profiles,
                        thresholds=source.thresholds, frames=1)
    rows = [measure(name, m) for name in a.strategies]
    for r in rows:
        print(f"{r['strategy']:<11} counted {r['counted_bytes']:>8,} B   orders {r['order_bytes']:>8,} B   reports "
              f"{r['report_bytes']:>8,} B   wire/counted {r['wire_over_counted']:6.2f}x   framing "
              f"{r['framing_per_message']:7.1f} B/message ({r['messages']} order+report pairs)   own logs "
              f"{r['logged_bytes']:>9,} B")
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps({"cpu": platform.processor() or platform.machine(), "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
