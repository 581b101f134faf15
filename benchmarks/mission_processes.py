"""A mission on real processes against the same mission in process: wall time, time per
sync round, and memory per process (``fedmap mission --deploy local``).

    python benchmarks/mission_processes.py                      # predictive, 4 rovers
    python benchmarks/mission_processes.py --rovers 4 16        # and 16
    python benchmarks/mission_processes.py --strategy raw --steps 100

For each team size: the strategy's mission in process (:func:`fedmap.mission.run_mission`),
then on processes (a SuperLink, one rover process per rover, the ServerApp, TLS and
authentication on 127.0.0.1). Prints the strategy's own run time both ways and their
ratio, the start-up (processes, certificates, every rover connected), the time per sync
round, and the memory of every process of the deployment by kind (peak PSS and RSS, sampled
every 0.5 s; PSS shares each page among the processes that map it, so the forked rovers'
shared pages are not counted once per process as RSS counts them) and of all of them at
once, and checks that both ways recorded the same mission. Writes
``benchmarks/results/mission_processes.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import threading
import time
from pathlib import Path

from fedmap.flower.mission.deploy import LOCAL_POLL, deploy_mission
from fedmap.mission import load_mission, mission_terrain, run_mission
from fedmap.mission.outputs.report import metrics, without_timings
from fedmap.mission.settings import mission_toml

OUT = Path(__file__).resolve().parent / "results" / "mission_processes.json"


def _descendants(root: int) -> list[int]:
    children: dict[int, list[int]] = {}
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                ppid = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            children.setdefault(ppid, []).append(int(d.name))
    out, todo = [], [root]
    while todo:
        p = todo.pop()
        for c in children.get(p, []):
            out.append(c)
            todo.append(c)
    return out


def _kind(pid: int) -> str | None:
    try:
        cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return None
    for key, kind in (("fedmap.flower.superlink", "SuperLink (and its front)"),
                      ("flower-superlink", "SuperLink"), ("flwr-serverapp", "ServerApp (base station)"),
                      ("fedmap.flower.supernode", "SuperNode"), ("flower-superexec", "SuperExec"),
                      ("flwr-clientapp", "ClientApp stand-in"), ("fedmap rover", "rover (and its warm ClientApps)"),
                      # a fork keeps its parent's command line: the host, its rovers, their warm servers and SuperNodes
                      ("fedmap.cli.rover_host", "host of rovers and its forks")):
        if key in cmd:
            return kind
    return None


def _rollup(pid: int) -> tuple[int, int] | None:
    """(RSS, PSS) of ``pid`` in kB (``/proc/PID/smaps_rollup``). RSS counts every page the
    process maps, so the pages forked rovers share with the host of rovers are counted once per
    process; PSS splits each shared page among the processes sharing it: their sum is what the
    deployment really holds."""
    try:
        fields = {ln.split(":")[0]: int(ln.split()[1]) for ln in Path(f"/proc/{pid}/smaps_rollup").read_text()
                  .splitlines()[1:] if ln.split()[1].isdigit()}
        return fields["Rss"], fields["Pss"]
    except (OSError, KeyError, IndexError, ValueError):
        return None


class Sampler(threading.Thread):
    """Peak RSS and PSS of every process under this one, by kind, and the peak of their sums
    (all processes at one instant), every 0.5 s."""

    def __init__(self) -> None:
        super().__init__(daemon=True)
        self.peak: dict[int, tuple[str, int, int]] = {}
        self.total_rss = self.total_pss = self.processes = 0
        self.stop = threading.Event()

    def run(self) -> None:
        while not self.stop.is_set():
            rss_now = pss_now = n = 0
            for pid in _descendants(os.getpid()):
                kind = _kind(pid)
                got = _rollup(pid) if kind is not None else None
                if kind is None or got is None:
                    continue
                rss, pss = got
                rss_now, pss_now, n = rss_now + rss, pss_now + pss, n + 1
                _, r0, p0 = self.peak.get(pid, ("", 0, 0))
                self.peak[pid] = (kind, max(r0, rss), max(p0, pss))
            if pss_now > self.total_pss:
                self.total_rss, self.total_pss, self.processes = rss_now, pss_now, n
            self.stop.wait(0.5)

    def by_kind(self) -> dict[str, dict]:
        kinds: dict[str, list[tuple[int, int]]] = {}
        for kind, rss, pss in self.peak.values():
            kinds.setdefault(kind, []).append((rss, pss))
        out = {}
        for k, v in sorted(kinds.items()):
            pss = sorted(p for _, p in v)
            out[k] = {"processes": len(v), "peak_rss_mb_max": round(max(r for r, _ in v) / 1024, 1),
                      "peak_pss_mb_max": round(pss[-1] / 1024, 1), "peak_pss_mb_median": round(pss[len(pss) // 2] / 1024, 1)}
        return out


def one(strategy: str, rovers: int, steps: int, poll: float) -> dict:
    config, source, resolved = load_mission(overrides=[{"mission": {"rovers": rovers, "steps": steps,
                                                                    "strategies": [strategy]}}])
    truth, elevation, prior, profiles = mission_terrain(config, source)
    t0 = time.perf_counter()
    here = run_mission(config, truth, elevation=elevation, prior=prior, profiles=profiles,
                       thresholds=source.thresholds, frames=1)
    inproc = time.perf_counter() - t0
    rounds = len(config.sync_steps) + 1
    sampler = Sampler()
    sampler.start()
    started: list[float] = []
    with tempfile.TemporaryDirectory(prefix="fedmap-mission-processes-") as tmp:
        t1 = time.perf_counter()
        apart = deploy_mission(mission_toml(resolved), members=rovers, out=Path(tmp) / "out", strategies=(strategy,),
                               frames=1, rounds=rounds, poll=poll,
                               on_status=lambda st: started.append(time.perf_counter()) if not started else None)
        total = time.perf_counter() - t1
    sampler.stop.set()
    sampler.join()
    same = without_timings(metrics(here)["strategies"]) == without_timings(metrics(apart)["strategies"])
    run_s = apart.runs[strategy].seconds
    row = {"strategy": strategy, "rovers": rovers, "steps": steps, "sync_rounds": rounds - 1, "poll_s": poll,
           "in_process_s": round(here.runs[strategy].seconds, 2), "in_process_wall_s": round(inproc, 2),
           "on_processes_run_s": round(run_s, 2), "on_processes_wall_s": round(total, 2),
           "start_up_s": round((started[0] - t1) if started else float("nan"), 2),
           "ratio_run": round(run_s / here.runs[strategy].seconds, 2),
           "ratio_wall": round(total / inproc, 2), "per_round_s": round(run_s / rounds, 3),
           "same_metrics": same, "memory": sampler.by_kind(),
           "memory_total": {"processes": sampler.processes, "pss_mb": round(sampler.total_pss / 1024, 1),
                            "rss_mb": round(sampler.total_rss / 1024, 1)}}
    print(f"{strategy}, {rovers} rovers, {steps} steps ({rounds - 1} syncs), polls every {poll} s: "
          f"in process {row['in_process_s']} s; "
          f"on processes {row['on_processes_run_s']} s ({row['ratio_run']}x; {row['per_round_s']} s a round), "
          f"{row['on_processes_wall_s']} s with start-up {row['start_up_s']} s ({row['ratio_wall']}x wall); "
          f"same metrics: {same}")
    for kind, m in row["memory"].items():
        print(f"    {kind:34s} {m['processes']:3d} processes, peak PSS {m['peak_pss_mb_median']:.0f} MB median, "
              f"{m['peak_pss_mb_max']:.0f} MB max (RSS {m['peak_rss_mb_max']:.0f} MB max)")
    t = row["memory_total"]
    print(f"    all {t['processes']} processes at the peak: PSS {t['pss_mb']:.0f} MB (what they hold), "
          f"RSS {t['rss_mb']:.0f} MB (shared pages counted once per process)")
    return row


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rovers", type=int, nargs="+", default=[4])
    p.add_argument("--strategy", default="predictive")
    p.add_argument("--steps", type=int, default=150)
    p.add_argument("--poll", type=float, default=LOCAL_POLL, help="seconds between a rover's polls when idle")
    p.add_argument("--out", type=Path, default=OUT, help=f"the JSON written (default {OUT.name} in results/)")
    a = p.parse_args()
    rows = [one(a.strategy, n, a.steps, a.poll) for n in a.rovers]
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps({"cpu": platform.processor() or platform.machine(), "cores": os.cpu_count(),
                                 "rows": rows}, indent=1))
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
