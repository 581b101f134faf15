"""``fedmap mission``: rovers explore over time and share maps over a constrained link; the
ways of sharing side by side (:mod:`fedmap.mission`). This module only wires options."""

from __future__ import annotations

import time
import tomllib
from contextlib import nullcontext
from pathlib import Path
from typing import Any, Optional

import typer
from rich.markup import escape
from rich.table import Table

from fedmap import _schema
from fedmap._util import check_output_dir, cpu_cores, to_json
from fedmap.cli.options import SHORTCUT_FLAGS, parameters, with_settings
from fedmap.cli.ui import console, fit, progress_bar, terrain_line
from fedmap.errors import FedmapError
from fedmap.flower.checkpoint import run_dir
from fedmap.flower.mission.deploy import DEPLOY_MODES, deploy_logs, deploy_mission
from fedmap.maps.rosbag import check_bag_path
from fedmap.maps.sources import terrain_notes
from fedmap.mission import load_mission, mission_terrain
from fedmap.mission.network.peers import peer_strategies
from fedmap.mission.network.remote import deployable_strategies
from fedmap.mission.outputs.bag import SyncMaps
from fedmap.mission.outputs.maps_out import MAPS_DIR
from fedmap.mission.outputs.recording import Recorder, check_recording_path
from fedmap.mission.outputs.report import global_meaning, has_peers, repeat_rows, table_rows, verdict, write_mission
from fedmap.mission.repeats import run_repeats, what_varies
from fedmap.mission.results import movement_warnings
from fedmap.mission.scoring import MISSION_FILE, MissingLog, score_folder
from fedmap.mission.settings import MISSION_SECTIONS, mission_toml, parse_sets
from fedmap.mission.sim import start_pocket_warning
from fedmap.pipeline import PipelineConfig

#: ``mission``'s generated options: the top-level seed, the terrain and threshold settings
#: exactly as ``run``'s, then [mission] and [link].
_SETTINGS = [*(s for s in _schema.walk(PipelineConfig) if s.section in ("", "terrain", "thresholds") and s.name != "method"),
             *(s for name, cls in MISSION_SECTIONS.items() for s in _schema.settings(cls, name))]


#: Where ``--deploy base`` listens unless ``--listen`` says otherwise.
DEFAULT_LISTEN = "127.0.0.1:9092"


@with_settings(parameters(_SETTINGS, skip=SHORTCUT_FLAGS), terrain=True)
def mission(
    config: Optional[Path] = typer.Argument(None, help=escape("Mission TOML ([terrain], [thresholds], [mission], [link], [strategies.*]); default: built-in mars 128².")),
    preset: Optional[str] = typer.Option(None, help="A shipped mission preset laid under the file, e.g. cadre."),
    set_: Optional[list[str]] = typer.Option(None, "--set", help="Any mission key: section.key=value (TOML value), e.g. mission.rovers=3; repeatable."),
    animation: bool = typer.Option(True, "--animation/--no-animation", help="Write the GIF (and MP4 with ffmpeg) of each strategy."),
    export: bool = typer.Option(False, "--export", help="Also write every rover's final belief under maps/ (each strategy's final global map is always written: PNG, GeoTIFF, ROS map)."),
    repeats: int = typer.Option(1, "--repeats", min=1, help="Run the mission N times, each with its own seeds (evaluation pairs, losses, noise, starts in the start area); report means with 95 % intervals."),
    out: Path = typer.Option(Path("fedmap-out/mission"), "--out", "-o", help="Output folder (replaced atomically)."),
    record: Optional[Path] = typer.Option(None, "--record", help="Also write the mission as an MCAP recording for Foxglove (every strategy's maps, rovers, link messages and scores; with --repeats, repeat 1's)."),
    live: bool = typer.Option(False, "--live/--no-live", help="Stream the same channels from a Foxglove WebSocket server while the mission runs (stopped at the end)."),
    rosbag: Optional[Path] = typer.Option(None, "--rosbag", help="Also write every strategy's global map and every rover's belief at step 0, every sync and the last step as a ROS 2 bag folder of nav_msgs/OccupancyGrid (1 s a step; with --repeats, repeat 1's)."),
    port: int = typer.Option(8765, "--port", min=0, max=65535, help="The --live server's port on 127.0.0.1 (0: any free port)."),
    deploy: Optional[str] = typer.Option(None, "--deploy", help="Run the mission on real processes: zenoh (one process per rover over Zenoh on this machine, mutual TLS and access control), or with Flower local (a SuperLink, one rover process per rover and the base station on this machine, TLS and authentication) or base (only the base station; rovers join with fedmap rover --mission). Star topology, latency 0."),
    listen: Optional[str] = typer.Option(None, "--listen", help="--deploy base: the SuperLink's HOST:PORT (rovers connect to it) [127.0.0.1:9092]."),
    certs: Optional[Path] = typer.Option(None, "--certs", help="--deploy base: TLS folder from fedmap certs (ca.crt, server.pem, server.key)."),
    auth_keys: Optional[Path] = typer.Option(None, "--auth-keys", help="--deploy base: folder of the rovers' *.pub keys (SuperNode authentication)."),
    resume: bool = typer.Option(False, "--resume", help="--deploy: carry on from the base station's journal of an earlier run into the same --out that was killed (the rovers carry on from their state folders)."),
    step_seconds: float = typer.Option(0.0, "--step-seconds", min=0.0, help="--deploy: every node on its own clock, a step every this many seconds (a rover drives on its own and syncs at its own sync steps; the base station runs its rounds on its clock). 0: lockstep, the base orders every step (the same mission as in process)."),
    insecure: bool = typer.Option(False, "--insecure", help="--deploy base: listen beyond this machine without TLS or authentication (a trusted network only)."),
    workers: int = typer.Option(0, "--workers", min=0, help="Run the strategies side by side in this many processes (0: one per CPU core this process may use); the results are the same. With --record, --live or --rosbag they run one after another."),
    settings: Optional[dict] = None,
    terrain: Optional[dict] = None,
) -> None:
    """Run one mission with every sharing strategy; write metrics.json, report.md, plots and animations."""
    t0 = time.perf_counter()
    cfg, source, resolved = load_mission(config, preset=preset, terrain=terrain,
                                         overrides=[*parse_sets(set_), settings or {}])
    _check_outputs(out, record=record, rosbag=rosbag)
    plan = None
    if deploy is None:  # options of a mission on processes, given without one: a mistake, not ignored
        alone = [o for o, on in (("--listen", listen is not None), ("--resume", resume), ("--certs", certs is not None),
                                 ("--auth-keys", auth_keys is not None), ("--insecure", insecure),
                                 ("--step-seconds", step_seconds > 0)) if on]
        if alone:
            raise FedmapError(f"{', '.join(alone)} apply to a mission on processes only: add --deploy zenoh, local or base")
    else:
        inprocess = [o for o, on in (("--repeats", repeats > 1), ("--record", record is not None), ("--live", live),
                                     ("--rosbag", rosbag is not None)) if on]
        if inprocess:
            raise FedmapError(f"{', '.join(inprocess)} run in process only, not with --deploy")
        plan = _deploy_plan(cfg, deploy, listen or DEFAULT_LISTEN)  # before the terrain loads: a wrong argument costs nothing
        base_only = [o for o, on in (("--listen", listen is not None), ("--certs", certs is not None),
                                     ("--auth-keys", auth_keys is not None), ("--insecure", insecure)) if on]
        if deploy == "zenoh" and base_only:
            raise FedmapError(f"{', '.join(base_only)} apply to --deploy base; --deploy zenoh runs the team on this "
                              "machine with its own certificates (a base on its own computer: fedmap node base)")
    with progress_bar() as progress:
        task = progress.add_task("load terrain", total=None, loss="")
        truth, elevation, prior, profiles = mission_terrain(cfg, source)
        for warning in (*terrain_notes(truth), start_pocket_warning(truth, cfg)):
            if warning:
                console.print(f"warning: {warning}", soft_wrap=True)  # one line, however wide

        if repeats > 1:
            console.print(f"repeats: {what_varies(cfg, repeats)}", soft_wrap=True)
        label = ""
        recorder = Recorder(cfg, truth, mcap=record, live=live, port=port, elevation=elevation) \
            if record is not None or live else None
        if recorder is not None and recorder.url:
            console.print(f"live: {recorder.url}  (Foxglove: open connection, Foxglove WebSocket; layout "
                          "docs/foxglove_layout.json)", soft_wrap=True)
        first = True

        def on_repeat(i: int, _config) -> None:
            nonlocal label, first
            label = f"repeat {i + 1}/{repeats}: " if repeats > 1 else ""
            first = i == 0

        bag = SyncMaps(cfg, truth) if rosbag is not None else None

        def on_snapshot(snapshot) -> None:  # the recording, the live view and the bag hold repeat 1
            if first and recorder is not None:
                recorder.log(snapshot)
            if first and bag is not None:
                bag(snapshot)

        tasks: dict[str, Any] = {}  # strategy -> its bar (strategies may run side by side)

        def on_strategy(name: str) -> None:
            tasks[name] = progress.add_task(f"{label}mission: {name}", total=cfg.steps, loss="", alongside=True)

        def on_step(name: str, step: int, coverage: float) -> None:
            if cfg.stops(step, coverage):  # the stop rule ends this run here: so does its bar
                progress.update(tasks[name], total=step, completed=step, loss=f"stopped: reachable {coverage:.0%}")
            else:
                progress.update(tasks[name], completed=step, loss=f"reachable {coverage:.0%}")

        if deploy is not None:
            assert plan is not None
            try:
                results = [_deployed(cfg, resolved, deploy, plan, out=out, animation=animation, progress=progress,
                                     certs=certs, auth_keys=auth_keys, insecure=insecure, resume=resume,
                                     step_seconds=step_seconds)]
            except MissingLog:  # --deploy base: the rovers keep their logs on their own machines
                if deploy != "base":
                    raise
                run = run_dir(out)
                console.print(f"mission over. Each rover keeps its own log (log/ in its --state folder): copy them into "
                              f"{run}/, then score the mission with: fedmap score {run} -o {out}", soft_wrap=True)
                return
        else:
            with recorder if recorder is not None else nullcontext():  # stops the server, keeps the MCAP only on success
                results = run_repeats(cfg, truth, repeats, on_repeat=on_repeat, elevation=elevation, prior=prior,
                                      profiles=profiles, thresholds=source.thresholds, on_strategy=on_strategy,
                                      on_step=on_step,
                                      on_snapshot=on_snapshot if recorder is not None or bag is not None else None,
                                      frames=60 if animation else 1,  # without an animation, keep no frames' maps
                                      workers=workers or cpu_cores())
        result = results[0]
        for warning in movement_warnings(result):
            console.print(f"warning: {warning}", soft_wrap=True)
        task = progress.add_task("write outputs", total=None, loss="")
        title = f"{source.label}, {truth.shape[0]}x{truth.shape[1]}"
        extra = {"mission.toml": mission_toml(resolved), "mission.json": to_json(resolved)}
        if deploy is not None:
            extra.update(deploy_logs(out))
        write_mission(result, out, title=title, settings=resolved, animation=animation, repeats=results, beliefs=export,
                      extra=extra)
        if bag is not None:
            bag.write(rosbag)
        progress.update(task, total=1, completed=1)
    if rosbag is not None:
        console.print(f"ROS 2 bag: {rosbag}/  (ros2 bag play {rosbag})")
    if record is not None:
        console.print(f"recording: {record}  (MCAP{', repeat 1' if repeats > 1 else ''}; Foxglove layout: "
                      "docs/foxglove_layout.json)")
    if repeats > 1:
        _print_repeats(results, title)
        console.print(verdict(result, results).replace("**", ""), soft_wrap=True)
        console.print(f"outputs: {out}/  (metrics.json with every repeat, report.md, {_maps(out)}coverage.png, f1.png, "
                      f"accuracy_bytes.png, knowing.png{', mission_<strategy>.gif of repeat 1' if animation else ''})")
        console.print(f"wall time: {time.perf_counter() - t0:.1f} s")
        return
    header, rows = table_rows(result)
    t = Table(title=f"mission on {title}: strategies side by side", header_style="bold")
    peer = has_peers(result)
    keep = [i for i, h in enumerate(header) if h in _CONSOLE or (peer and h in _CONSOLE_PEER) or h in _CONSOLE_HEIGHTS]
    if peer:  # on a peer topology the uplink column is empty: its messages are peer messages
        keep = [i for i in keep if header[i] != "uplinks not delivered"]
    names = {**_CONSOLE, **_CONSOLE_PEER, **_CONSOLE_HEIGHTS}
    for i in keep:
        t.add_column(names[header[i]], justify="left" if i == 0 else "right", no_wrap=True)
    for r in rows:
        t.add_row(*(r[i] for i in keep))
    console.print(fit(t))
    console.print(terrain_line(source.label, truth, source.thresholds))
    reach = next(iter(result.runs.values())).summary.reachable_share
    console.print("50/80/95 %: first step the team had observed that share of the cells it can reach "
                  f"({reach:.0%} of the map); F1>=.9: first step a rover's belief gave "
                  "strict A* path F1 >= 0.9; cov., reach., acc.: coverage of the map and of the cells the team can "
                  "reach, and mean belief accuracy at the end; f.free: share of the cells "
                  f"a rover plans on as free that are impassable; glob.F1: {global_meaning(result)}, strict; team "
                  "up/down B: bytes of the whole team over the mission (a rover's sends; the base's or lander's sends)"
                  + ("; B/link/rnd: mean bytes per message on a link that was up; peer lost: peer messages that did "
                     "not arrive, by why" if peer else "; up lost/over: uplink messages that did not arrive, by why")
                  + ". All columns: report.md.")
    console.print(verdict(result).replace("**", ""), soft_wrap=True)
    console.print(f"outputs: {out}/  (metrics.json, report.md, {_maps(out)}coverage.png, f1.png, accuracy_bytes.png, "
                  f"knowing.png{', mission_<strategy>.gif' if animation else ''})")
    console.print(f"wall time: {time.perf_counter() - t0:.1f} s")


def _deploy_plan(cfg, mode: str, listen: str) -> tuple[tuple[str, ...], list[str], str, str]:
    """What ``--deploy mode`` runs, checked: the strategies that run on processes, those left
    out, and ``--listen``'s host and port."""
    if mode not in (*DEPLOY_MODES, "zenoh"):
        raise FedmapError(f"unknown --deploy {mode!r}: choose one of {', '.join((*DEPLOY_MODES, 'zenoh'))}")
    if mode == "zenoh" and cfg.link.topology != "star":  # a peer mission: an agent per process
        names, left = peer_strategies(cfg)
    else:
        names, left = deployable_strategies(cfg)  # before any process starts
    host, _, port = listen.rpartition(":")
    if mode == "base" and not (host and port.isdigit()):
        raise FedmapError(f"--listen must be HOST:PORT, got {listen!r}")
    return names, left, host, port


def _maps(out: Path) -> str:
    """``maps/, `` in the outputs line when the run wrote that folder (a mission whose strategies
    shared nothing has no global map to write)."""
    return f"{MAPS_DIR}/, " if (out / MAPS_DIR).is_dir() else ""


def _check_outputs(out: Path, *, record: Path | None, rosbag: Path | None) -> None:
    """Before any work: the output folder can be replaced (:func:`check_output_dir`), the bag
    written, and neither the recording nor the bag lies inside the output folder, which the run
    replaces as a whole at its end (they would go with the old folder)."""
    folder = check_output_dir(out)
    for option, path in (("--record", record), ("--rosbag", rosbag)):
        if path is not None and Path(path).expanduser().resolve().is_relative_to(folder):
            raise FedmapError(f"{option} {path} is inside the output folder {out}, which the run replaces as a whole; "
                              "write it elsewhere")
    if rosbag is not None:
        check_bag_path(rosbag)
    if record is not None:
        check_recording_path(record)


def _deployed(cfg, resolved: dict, mode: str, plan: tuple[tuple[str, ...], list[str], str, str], *, out: Path,
              animation: bool, progress, certs: Optional[Path], auth_keys: Optional[Path], insecure: bool, resume: bool,
              step_seconds: float = 0.0):
    """The mission on real processes (:func:`fedmap.flower.mission.deploy.deploy_mission`) as
    :func:`_deploy_plan` planned it, with a progress bar per strategy from the base station's status."""
    names, left, host, port = plan
    if left:
        console.print(f"note: {', '.join(left)} stay(s) out of a mission on processes (not one end per machine)")
    members = cfg.rovers + cfg.helicopters
    if mode == "zenoh":
        return _over_zenoh(cfg, resolved, names, out=out, animation=animation, progress=progress, resume=resume,
                           step_seconds=step_seconds)
    start = progress.add_task(f"start the SuperLink, {members} rover processes and the base station" if mode == "local"
                              else "start the SuperLink and the base station; wait for the rovers", total=None, loss="")
    tasks: dict[str, int] = {}

    def on_status(st: dict) -> None:
        name = st.get("strategy")
        if name and not tasks:
            progress.update(start, total=1, completed=1)
        if name and name not in tasks:
            tasks[name] = progress.add_task(f"mission on processes: {name}", total=cfg.steps, loss="")
        if name:
            progress.update(tasks[name], completed=st.get("step", 0), loss="")

    def on_ready(address: str) -> None:
        if mode == "base":
            console.print(f"base station listening on {address}; start each rover k with: fedmap rover --mission "
                          f"--partition-id k --superlink {address} [--root-cert ca.crt --auth-key roverk]",
                          soft_wrap=True)

    return deploy_mission(mission_toml(resolved), members=members, out=out, mode=mode,
                          strategies=names, frames=60 if animation else 1,
                          host=host if mode == "base" else "127.0.0.1", port=int(port) if mode == "base" else 0,
                          certs=certs, auth_keys=auth_keys, insecure=insecure, rounds=len(cfg.sync_steps) + 1,
                          resume=resume, step_seconds=step_seconds,
                          on_status=on_status, on_ready=on_ready)


def _over_zenoh(cfg, resolved: dict, names: tuple[str, ...], *, out: Path, animation: bool, progress, resume: bool,
                step_seconds: float):
    """The mission with one process per rover over Zenoh on this machine
    (:func:`fedmap.zenohnet.deploy.deploy_zenoh`), a progress bar per strategy."""
    from fedmap.zenohnet.deploy import deploy_zenoh

    members = cfg.rovers + cfg.helicopters
    start = progress.add_task(f"start {members} rover processes (Zenoh, mutual TLS)", total=None, loss="")
    tasks: dict[str, int] = {}

    def on_started(seconds: float) -> None:
        progress.update(start, total=1, completed=1, loss=f"{seconds:.1f} s")

    def on_step(name: str, step: int) -> None:
        if name not in tasks:
            tasks[name] = progress.add_task(f"mission over Zenoh: {name}", total=cfg.steps, loss="")
        progress.update(tasks[name], completed=step)

    return deploy_zenoh(mission_toml(resolved), members=members, out=out, strategies=names,
                        frames=60 if animation else 1, resume=resume, step_seconds=step_seconds,
                        on_step=on_step, on_started=on_started)


def _print_repeats(results: list, title: str) -> None:
    """The console table of a repeated mission: each value's mean and 95 % interval."""
    header, rows = repeat_rows(results)
    t = Table(title=f"mission on {title}: strategies side by side, mean [95 % interval] of {len(results)} repeats",
              header_style="bold")
    for i, h in enumerate(header):
        t.add_column(h, justify="left" if i == 0 else "right")
    for r in rows:
        t.add_row(*r)
    console.print(fit(t))
    guessed = "guessed F1≥0.9 at" in header
    console.print("team F1≥0.9 at: first step the rovers' mean belief F1 (strict A* path F1) reached 0.9; "
                  + ("guessed F1≥0.9 at: the same, of their beliefs with the predictor's guesses filled in; "
                     if guessed else "")
                  + "plannable at: first step it had and coverage was 95 %; bytes: the whole team's, both ways. A "
                  "step some repeats never reached gives the mean of those that did and (how many/repeats).",
                  soft_wrap=True)


#: Columns of the console table (report.md has them all) -> their short headers.
_CONSOLE = {"strategy": "strategy", "steps to 50 %": "50 %", "steps to 80 %": "80 %", "steps to 95 %": "95 %",
            "belief F1≥0.9 at": "F1>=.9", "coverage": "cov.", "reachable coverage": "reach.", "belief acc.": "acc.",
            "false-free": "f.free",
            "global F1": "glob.F1",
            "team bytes up": "team up B", "team bytes down": "team down B", "uplinks not delivered": "up lost/over"}
#: Console columns of a mission with an elevation layer.
_CONSOLE_HEIGHTS = {"base height RMSE m": "z RMSE m"}
#: Console columns of a mission with peer messages (mesh, leader, gossip).
_CONSOLE_PEER = {"B/link/round": "B/link/rnd", "peer messages not delivered": "peer lost"}


def score(
    run_folder: Path = typer.Argument(..., help="A mission's run folder (<out>.run of fedmap mission --deploy): the base station's records, with every rover's log copied anywhere into it."),
    out: Path = typer.Option(Path("fedmap-out/mission"), "--out", "-o", help="Output folder (replaced atomically)."),
    animation: bool = typer.Option(True, "--animation/--no-animation", help="Write the GIF (and MP4 with ffmpeg) of each strategy."),
) -> None:
    """Score a mission from what its nodes logged (the rovers' logs and the base station's records) against the truth; write metrics.json, report.md, plots and maps as fedmap mission does."""
    t0 = time.perf_counter()
    check_output_dir(out)
    try:
        text = (Path(run_folder) / MISSION_FILE).read_text()
    except FileNotFoundError:
        raise FedmapError(f"{run_folder} is not a mission's run folder: no {MISSION_FILE}") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise FedmapError(f"{Path(run_folder) / MISSION_FILE} is not valid TOML: {e}") from None
    cfg, source, resolved = load_mission(None, overrides=[data])
    with progress_bar() as progress:
        tasks: dict[str, Any] = {}

        def on_step(name: str, step: int, coverage: float) -> None:
            if name not in tasks:
                tasks[name] = progress.add_task(f"score: {name}", total=cfg.steps, loss="")
            progress.update(tasks[name], completed=step, loss=f"coverage {coverage:.0%}")

        result = score_folder(Path(run_folder), frames=60 if animation else 1, on_step=on_step)
        task = progress.add_task("write outputs", total=None, loss="")
        title = f"{source.label}, {result.truth.shape[0]}x{result.truth.shape[1]}"
        write_mission(result, out, title=title, settings=resolved, animation=animation,
                      extra={"mission.toml": text, "mission.json": to_json(resolved)})
        progress.update(task, total=1, completed=1)
    console.print(verdict(result).replace("**", ""), soft_wrap=True)
    console.print(f"outputs: {out}/  (metrics.json, report.md, coverage.png, f1.png, accuracy_bytes.png, knowing.png)")
    console.print(f"wall time: {time.perf_counter() - t0:.1f} s")
