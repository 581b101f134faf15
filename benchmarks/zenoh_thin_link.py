"""A mission over Zenoh across an OS-level thin link: the base station in a network namespace
of its own, joined to the rovers by a veth pair rate-limited with ``tc tbf`` both ways
(250 kbit/s by default: Ingenuity's Zigbee link), against the same mission in process.

    sudo python benchmarks/zenoh_thin_link.py [--rate 250kbit] [--loss 0.05] [--steps 300] [--strategies raw,predictive]
    sudo python benchmarks/zenoh_thin_link.py --topology leader --strategies raw,gossip

Needs root (``ip netns``, ``tc``). It makes namespace ``fm-base`` with ``veth-fm-b``
(10.77.0.1) and leaves ``veth-fm-r`` (10.77.0.2) in this namespace, puts a token-bucket
filter on both ends (and with ``--loss`` an nftables rule that drops that share of the
base's packets at random both ways: TCP sends them again, so the link loses time, not
messages), runs ``fedmap node base`` inside it and four ``fedmap node rover``
processes outside, scores the mission from the nodes' logs, and removes the namespace.
It prints, per strategy, the bytes the link model counted (the strategy's messages), the
wire bytes (orders and reports, framing included), the time on the base's clock over the
thin link, over loopback and in process, and whether the final maps and metrics equal the
in-process mission's (in lockstep the link model decides every message's fate, so they
must; the thin link costs time). Results go to ``benchmarks/results/zenoh_thin_link/``.

With ``--topology mesh`` or ``leader`` the team is peers: the lander (``fedmap node base``,
the team's router and an agent) in the namespace and four ``fedmap node peer`` outside, so
every mail between agents crosses the thin link; its wire bytes are the mail the agents
posted (positions, messages and answers).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
import tomllib
from pathlib import Path

import numpy as np

from fedmap.mission import load_mission, mission_terrain, run_mission
from fedmap.mission.outputs.report import metrics, without_timings
from fedmap.mission.scoring import score_folder
from fedmap.mission.settings import mission_toml
from fedmap.zenohnet.deploy import deploy_zenoh

OUT = Path(__file__).resolve().parent / "results" / "zenoh_thin_link"
NS, BASE_IF, ROVER_IF, BASE_IP, ROVER_IP = "fm-base", "veth-fm-b", "veth-fm-r", "10.77.0.1", "10.77.0.2"


def sh(*argv: str) -> None:
    subprocess.run(argv, check=True)


def link_up(rate: str, loss: float = 0.0) -> None:
    link_down()
    sh("ip", "netns", "add", NS)
    sh("ip", "link", "add", ROVER_IF, "type", "veth", "peer", "name", BASE_IF)
    sh("ip", "link", "set", BASE_IF, "netns", NS)
    sh("ip", "addr", "add", f"{ROVER_IP}/24", "dev", ROVER_IF)
    sh("ip", "link", "set", ROVER_IF, "up")
    sh("ip", "netns", "exec", NS, "ip", "addr", "add", f"{BASE_IP}/24", "dev", BASE_IF)
    sh("ip", "netns", "exec", NS, "ip", "link", "set", BASE_IF, "up")
    sh("ip", "netns", "exec", NS, "ip", "link", "set", "lo", "up")
    for pre, dev in (([], ROVER_IF), (["ip", "netns", "exec", NS], BASE_IF)):
        sh(*pre, "tc", "qdisc", "add", "dev", dev, "root", "tbf", "rate", rate, "burst", "4kb", "latency", "400ms")
    if loss > 0:  # packets lost at random, both ways, on the base's side (nftables; netem is not available)
        ns = ["ip", "netns", "exec", NS, "nft"]
        sh(*ns, "add", "table", "inet", "fmloss")
        for hook in ("input", "output"):
            sh(*ns, "add", "chain", "inet", "fmloss", hook, f"{{ type filter hook {hook} priority 0 ; }}")
            sh(*ns, "add", "rule", "inet", "fmloss", hook, "iifname" if hook == "input" else "oifname", BASE_IF,
               "numgen", "random", "mod", "1000", "<", str(round(loss * 1000)), "drop")


def veth_bytes() -> int:
    """Bytes that crossed the thin link so far, both ways (the rovers' end's counters: IP, TCP and TLS included)."""
    stats = Path(f"/sys/class/net/{ROVER_IF}/statistics")
    return int((stats / "tx_bytes").read_text()) + int((stats / "rx_bytes").read_text())


def link_down() -> None:
    subprocess.run(["ip", "link", "del", ROVER_IF], capture_output=True)
    subprocess.run(["ip", "netns", "del", NS], capture_output=True)


def thin(text: str, tmp: Path, port: int, strategies: list[str], topology: str = "star") -> tuple[float, dict]:
    """The mission with the base in the namespace; (wall seconds, the scored result)."""
    (tmp / "mission.toml").write_text(text)
    out, work = tmp / "thin", tmp / "thin.run"
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    node = "rover" if topology == "star" else "peer"
    rovers = [subprocess.Popen([sys.executable, "-m", "fedmap", "node", node, "--rover", str(k), "--connect",
                                f"{BASE_IP}:{port}", "--team", "thin", "--state", str(work / f"rover{k}.state")],
                               env=env, stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT) for k in range(4)]
    t0 = time.perf_counter()
    try:
        subprocess.run(["ip", "netns", "exec", NS, sys.executable, "-m", "fedmap", "--quiet", "node", "base",
                        str(tmp / "mission.toml"), "--listen", f"{BASE_IP}:{port}", "--insecure", "--out", str(out),
                        "--team", "thin"], env=env, check=True, stdout=subprocess.DEVNULL)
        for r in rovers:
            r.wait(timeout=60)
    finally:
        for r in rovers:
            if r.poll() is None:
                r.kill()
    return time.perf_counter() - t0, score_folder(work, frames=1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rate", default="250kbit")
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--strategies", default="raw,predictive")
    ap.add_argument("--loss", type=float, default=0.0, help="share of packets dropped at random both ways (nftables)")
    ap.add_argument("--topology", default="star", choices=["star", "mesh", "leader"])
    ap.add_argument("--out", type=Path, default=OUT)
    a = ap.parse_args()
    if os.geteuid() != 0:
        sys.exit("error: needs root (ip netns, tc)")
    names = a.strategies.split(",")
    _, _, resolved = load_mission(overrides=[{"mission": {"steps": a.steps, "strategies": names},
                                              "link": {"topology": a.topology, "latency": 0}}])
    text = mission_toml(resolved)
    config, source, _ = load_mission(None, overrides=[tomllib.loads(text)])
    truth, elevation, prior, profiles = mission_terrain(config, source)
    here = run_mission(config, truth, elevation=elevation, prior=prior, profiles=profiles,
                       thresholds=source.thresholds, frames=1, workers=1)
    with tempfile.TemporaryDirectory() as tmp:
        loop = deploy_zenoh(text, members=config.rovers, out=Path(tmp) / "loop", strategies=tuple(names), frames=1,
                            tls=False)
        link_up(a.rate, a.loss)
        try:
            before = veth_bytes()
            wall, far = thin(text, Path(tmp), 7447, names, a.topology)
            crossed = veth_bytes() - before
        finally:
            link_down()
    rows = []
    same = without_timings(metrics(here)["strategies"]) == without_timings(metrics(far)["strategies"])
    for n in names:
        ledger = far.runs[n].ledger
        maps_equal = all(np.array_equal(a_, b_) for a_, b_ in zip(here.runs[n].views, far.runs[n].views))
        rows.append({"strategy": n, "ledger_bytes": sum(m.bytes for m in ledger),
                     "wire_bytes": (far.runs[n].wire or {}).get("mail_bytes", (far.runs[n].wire or {}).get("bytes")),
                     "thin_s": round(far.runs[n].seconds, 2), "loopback_s": round(loop.runs[n].seconds, 2),
                     "in_process_s": round(here.runs[n].seconds, 2), "final_maps_equal": maps_equal})
    result = {"rate": a.rate, "loss": a.loss, "steps": a.steps, "topology": a.topology, "wall_s": round(wall, 1),
              "link_bytes": crossed, "same_metrics": same, "rows": rows}
    print(json.dumps(result, indent=1))
    a.out.mkdir(parents=True, exist_ok=True)
    tag = ("" if a.topology == "star" else f"_{a.topology}") + ("_loss" if a.loss else "")
    (a.out / f"results{tag}.json").write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
