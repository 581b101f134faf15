"""A mission over Zenoh (one process per rover, mutual TLS, lockstep) against the same
mission in process: its time, its start-up, the time of a round, and each rover process's memory.

    python benchmarks/zenoh_overhead.py [--rovers 4 16 64] [--steps 300] [--strategy predictive]
    python benchmarks/zenoh_overhead.py --topology mesh --rovers 4 16 --strategy raw


For each team size: the in-process mission of that one strategy (``workers=1``: one process,
its time is the strategy's own); then the same mission with ``deploy_zenoh`` (the base here,
each rover a ``fedmap node rover`` process forked from a host that imported fedmap once). It
prints the start-up (until every rover is up), the strategy's time on the base's clock (its
rounds, start-up excluded) against the in-process time (the overhead), the median and 95th
percentile of a round (every order out, every report back: the rovers' own work included),
and the rovers' memory as PSS (proportional set size: a page shared by N processes counts 1/N
to each), read from ``/proc/<pid>/smaps_rollup`` at the mission's last round. It checks that the two
missions' metrics agree (timings aside). Results go to ``benchmarks/results/zenoh_overhead/``
(``results.json``, ``results.md``, ``overhead.png``; ``--figure-only`` draws the figure again).

With ``--topology mesh`` (or ``leader``) the team is peers: every rover a ``fedmap node peer``
process, the lander an agent in this process and the team's router, no orders
(:mod:`fedmap.zenohnet.peer`); a round is then the lander's time from one sync to the next
(the rovers' driving, the round's mail and the wait for the slowest agent). Results go to
``benchmarks/results/zenoh_overhead_<topology>/``.
"""

from __future__ import annotations

import argparse
import json
import platform
import re
import statistics
import tempfile
import time
import tomllib
from pathlib import Path

from fedmap.mission import load_mission, mission_terrain, run_mission
from fedmap.mission.network.nodelog import read_peer_records
from fedmap.mission.outputs.report import metrics, without_timings
from fedmap.mission.settings import mission_toml
from fedmap.zenohnet.deploy import deploy_zenoh

OUT = Path(__file__).resolve().parent / "results" / "zenoh_overhead"


def pss_mb(pid: int) -> float:
    """MB of PSS of process ``pid``."""
    text = (Path("/proc") / str(pid) / "smaps_rollup").read_text()
    return int(re.search(r"^Pss:\s+(\d+) kB", text, re.M).group(1)) / 1024


def _cmdline(proc: Path) -> bytes:
    try:
        return (proc / "cmdline").read_bytes()
    except OSError:
        return b""


def one(rovers: int, steps: int, strategy: str, topology: str = "star") -> dict:
    _, _, resolved = load_mission(overrides=[{"mission": {"steps": steps, "rovers": rovers, "strategies": [strategy]},
                                              "link": {"topology": topology, "latency": 0}}])
    text = mission_toml(resolved)
    config, source, _ = load_mission(None, overrides=[tomllib.loads(text)])
    truth, elevation, prior, profiles = mission_terrain(config, source)
    t0 = time.perf_counter()
    here = run_mission(config, truth, elevation=elevation, prior=prior, profiles=profiles,
                       thresholds=source.thresholds, frames=1, workers=1)
    wall_here = time.perf_counter() - t0
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "out"
        work = out.with_name("out.run")
        started: list[float] = []
        pss: list[float] = []
        host: list[float] = []  # the host the rovers were forked from (one per team)

        def on_step(name: str, step: int) -> None:
            if step >= steps - (topology != "star") and not pss:  # (peers: before they finish and exit)
                pss.extend(pss_mb(int((work / f"rover{k}.pid").read_text())) for k in range(rovers))
                rover0 = int((work / "rover0.pid").read_text())
                parent = int(Path(f"/proc/{rover0}/stat").read_text().rsplit(")", 1)[1].split()[1])
                if b"fedmap.cli.rover_host" in _cmdline(Path(f"/proc/{parent}")):
                    host.append(pss_mb(parent))

        t1 = time.perf_counter()
        apart = deploy_zenoh(text, members=rovers, out=out, strategies=(strategy,), frames=1,
                             on_started=started.append, on_step=on_step)
        wall_apart = time.perf_counter() - t1
        if topology == "star":
            log = (work / "base.log").read_text()
            rounds = [float(s) for s in re.findall(r"rovers answered in ([\d.]+) s", log)]
        else:  # the lander's own record: its time from one sync to the next
            lander = read_peer_records(work, "*", strategy)
            rounds = next(r.rounds for r in lander if r.agent == -1)
    same = without_timings(metrics(here)["strategies"]) == without_timings(metrics(apart)["strategies"])
    mine, theirs = here.runs[strategy].seconds, apart.runs[strategy].seconds
    return {"rovers": rovers, "steps": steps, "strategy": strategy, "topology": topology, "same_metrics": same,
            "in_process_s": round(mine, 3), "zenoh_s": round(theirs, 3), "overhead": round(theirs / mine, 3),
            "startup_s": round(started[0], 2), "wall_in_process_s": round(wall_here, 2),
            "wall_zenoh_s": round(wall_apart, 2), "rounds": len(rounds),
            "round_median_ms": round(statistics.median(rounds) * 1e3, 2),
            "round_p95_ms": round(sorted(rounds)[int(0.95 * (len(rounds) - 1))] * 1e3, 2),
            "in_process_round_ms": round(mine / max(len(rounds), 1) * 1e3, 2),
            "pss_mb_per_rover": round(statistics.mean(pss), 1) if pss else None,
            "pss_mb_max": round(max(pss), 1) if pss else None, "host_pss_mb": round(sum(host), 1),
            "rover_processes_seen": len(pss)}


def figure(rows: list[dict], path: Path, cpu: str) -> None:
    """Time (in process, over Zenoh) and PSS per rover against the team's size."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = [r["rovers"] for r in rows]
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 4))
    a.plot(n, [r["in_process_s"] for r in rows], "o-", label="in process (one process)")
    a.plot(n, [r["zenoh_s"] for r in rows], "s-", label="over Zenoh (a process per rover, mutual TLS)")
    for r in rows:
        a.annotate(f"{r['overhead']:.2f}x", (r["rovers"], r["zenoh_s"]), textcoords="offset points", xytext=(-12, -14),
                   fontsize=8)
    a.set(xscale="log", yscale="log", xlabel="rovers", ylabel="seconds (start-up excluded)",
          title=f"{rows[0]['strategy']} on the {rows[0].get('topology', 'star')}, {rows[0]['steps']} steps, lockstep")
    from matplotlib.ticker import NullFormatter, ScalarFormatter

    a.set_xticks(n, [str(x) for x in n])
    a.xaxis.set_minor_formatter(NullFormatter())
    a.yaxis.set_major_formatter(ScalarFormatter())
    a.yaxis.set_minor_formatter(NullFormatter())
    a.set_xlim(n[0] / 1.5, n[-1] * 1.5)
    a.set_yticks([t for t in (1, 2, 5, 10, 20, 50, 100, 200, 500) if t <= 2 * max(r["zenoh_s"] for r in rows)])
    a.legend(fontsize=8)
    b.bar([str(x) for x in n], [r["pss_mb_per_rover"] or 0 for r in rows], color="tab:orange")
    b.axhline(150, color="k", ls="--", lw=1, label="target: 150 MB")
    b.set(xlabel="rovers", ylabel="PSS per rover process (MB)", title="memory per rover")
    b.legend(fontsize=8, loc="upper left")
    fig.suptitle(f"A mission over Zenoh against in process ({cpu}, 2 cores)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rovers", type=int, nargs="+", default=[4, 16, 64])
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--strategy", default="predictive")
    ap.add_argument("--topology", default="star", choices=["star", "mesh", "leader"])
    ap.add_argument("--out", type=Path, default=None, help="default: results/zenoh_overhead[_<topology>]/")
    ap.add_argument("--figure-only", action="store_true", help="draw overhead.png from --out's results.json")
    a = ap.parse_args()
    a.out = a.out or (OUT if a.topology == "star" else OUT.with_name(f"zenoh_overhead_{a.topology}"))
    if a.figure_only:
        saved = json.loads((a.out / "results.json").read_text())
        figure(saved["rows"], a.out / "overhead.png", saved["cpu"])
        return
    rows = []
    for n in a.rovers:
        row = one(n, a.steps, a.strategy, a.topology)
        rows.append(row)
        print(json.dumps(row), flush=True)
    cpu = next((ln.split(":", 1)[1].strip() for ln in Path("/proc/cpuinfo").read_text().splitlines()
                if ln.startswith("model name")), platform.processor())
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / "results.json").write_text(json.dumps({"cpu": cpu, "rows": rows}, indent=1))
    lines = [f"# A mission over Zenoh against in process ({a.strategy}, {a.topology}, {a.steps} steps; {cpu})", "",
             "| rovers | in process s | over Zenoh s | overhead | start-up s | round median ms | round p95 ms "
             "| in-process ms/round | PSS MB/rover | host PSS MB | same metrics |",
             "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|"]
    for r in rows:
        lines.append(f"| {r['rovers']} | {r['in_process_s']} | {r['zenoh_s']} | {r['overhead']}x | {r['startup_s']} | "
                     f"{r['round_median_ms']} | {r['round_p95_ms']} | {r['in_process_round_ms']} | "
                     f"{r['pss_mb_per_rover']} | {r['host_pss_mb']} | {r['same_metrics']} |")
    (a.out / "results.md").write_text("\n".join(lines) + "\n")
    figure(rows, a.out / "overhead.png", cpu)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
