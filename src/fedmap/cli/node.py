"""``fedmap node rover`` / ``fedmap node base``: one node of a team as its own process, over
Zenoh (:mod:`fedmap.zenohnet`). This module only wires options."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Optional

import typer
from rich.markup import escape

from fedmap.cli.ui import console, progress_bar
from fedmap.errors import FedmapError
from fedmap.flower.checkpoint import run_dir
from fedmap.mission.settings import parse_sets

node_app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False,
                       help="One node of a team as its own process on a robot or lander computer, over Zenoh.")


@node_app.command("rover")
def rover(
    rover_: int = typer.Option(..., "--rover", min=0, help="This rover's index in the team (0-based)."),
    connect: str = typer.Option(..., "--connect", help="The base station's HOST:PORT (or a Zenoh endpoint, tcp/HOST:PORT)."),
    team: str = typer.Option("fedmap", "--team", help="The team's name (teams can share a network); the base's --team."),
    state: Optional[Path] = typer.Option(None, "--state", help="Folder for this rover's own log (default: fedmap-rover<k>); the mission is scored from it."),
    certs: Optional[Path] = typer.Option(None, "--certs", help="TLS with mutual authentication: a folder with ca.crt, rover<k>.crt and rover<k>.key (from fedmap certs)."),
    feed: Optional[Path] = typer.Option(None, "--feed", help="Take this rover's observations from its own mapping software: a folder of map snapshots named with their step, or a ROS 2 bag of nav_msgs/OccupancyGrid."),
    feed_topic: Optional[str] = typer.Option(None, "--feed-topic", help="--feed: the bag's OccupancyGrid topic (default: its only one)."),
    fault: Optional[str] = typer.Option(None, hidden=True, help="Testing: corrupt@STEP damages one report."),
) -> None:
    """A rover node: answers the base station's orders (drive, sense, share) until the mission is over."""
    from fedmap.flower.mission.task import node_feed
    from fedmap.zenohnet.rover import serve_rover
    from fedmap.zenohnet.session import Certs, check_team, endpoint, node_config, open_session

    check_team(team)
    ep = endpoint(connect, tls=certs is not None)
    tls = Certs.for_node(certs, f"rover{rover_}") if certs is not None else None
    folder = state or Path(f"fedmap-rover{rover_}")
    mapfeed = node_feed({"feed": str(feed) if feed else "", "feed-topic": feed_topic or ""})
    session = open_session(node_config(connect=[ep], certs=tls))
    try:
        console.print(f"rover {rover_} of team {team}: connecting to {ep}; log in {folder}/log", soft_wrap=True)
        n = serve_rover(session, team, rover_, folder, feed=mapfeed, fault=fault,
                        say=lambda line: console.print(escape(line), soft_wrap=True))
    except KeyboardInterrupt:
        raise FedmapError(f"rover {rover_} stopped; its log is in {folder}/log") from None
    finally:
        session.close()
    console.print(f"rover {rover_}: mission over ({n} orders answered)")


@node_app.command("base")
def base(
    config: Optional[Path] = typer.Argument(None, help=escape("Mission TOML (as fedmap mission takes); default: built-in mars 128².")),
    preset: Optional[str] = typer.Option(None, help="A shipped mission preset laid under the file, e.g. cadre."),
    set_: Optional[list[str]] = typer.Option(None, "--set", help="Any mission key: section.key=value (TOML value); repeatable."),
    listen: str = typer.Option("127.0.0.1:7447", "--listen", help="HOST:PORT the base listens on (rovers connect to it)."),
    team: str = typer.Option("fedmap", "--team", help="The team's name (teams can share a network)."),
    certs: Optional[Path] = typer.Option(None, "--certs", help="TLS with mutual authentication and access control: a folder with ca.crt, server.pem and server.key (from fedmap certs)."),
    insecure: bool = typer.Option(False, "--insecure", help="Listen beyond this machine without TLS and access control (a trusted network only)."),
    out: Path = typer.Option(Path("fedmap-out/mission"), "--out", "-o", help="Where fedmap score writes the outputs; the run's own files go to OUT.run/."),
    resume: bool = typer.Option(False, "--resume", help="Carry on from the journal of a base station that was killed (the same mission and --out)."),
    step_seconds: float = typer.Option(0.0, "--step-seconds", min=0.0, help="Every node on its own clock, a step every this many seconds (0: lockstep)."),
    connect_timeout: float = typer.Option(300.0, "--connect-timeout", min=1.0, help="Seconds to wait for every rover to come up."),
) -> None:
    """The base station: waits for the team's rovers, runs the mission's clock, logs its side; score with fedmap score."""
    from fedmap.mission import load_mission
    from fedmap.mission.ends.registry import names_that
    from fedmap.mission.network.remote import check_deployable
    from fedmap.mission.settings import mission_toml
    from fedmap.zenohnet.base import ZenohTeam, run_base
    from fedmap.zenohnet.session import Certs, acl, check_listen, check_team, endpoint, node_config, open_session

    check_team(team)
    cfg, _source, resolved = load_mission(config, preset=preset, overrides=[*parse_sets(set_)])
    names = tuple(n for n in cfg.strategies if n in names_that("deployable"))
    if not names:
        raise FedmapError(f"none of the strategies {', '.join(cfg.strategies)} runs on processes; these do: "
                          f"{', '.join(names_that('deployable'))}")
    check_deployable(cfg, names)
    ep = endpoint(listen, tls=certs is not None)
    check_listen([ep], secure=certs is not None, insecure=insecure)
    members = cfg.rovers + cfg.helicopters
    tls = Certs.for_node(certs, "base") if certs is not None else None
    session = open_session(node_config(listen=[ep], certs=tls, access=None if tls is None else acl(team, members)))
    t0 = time.perf_counter()
    try:
        team_ = ZenohTeam(session, team, members, out)
        console.print(f"base station of team {team} listening on {ep}; start each rover k with: fedmap node rover "
                      f"--rover k --connect {listen}{' --certs DIR' if certs else ''}", soft_wrap=True)
        with progress_bar() as progress:
            tasks: dict[str, Any] = {}

            def on_step(name: str, step: int) -> None:
                if name not in tasks:
                    tasks[name] = progress.add_task(f"mission over Zenoh: {name}", total=cfg.steps, loss="")
                progress.update(tasks[name], completed=step)

            run_base(team_, mission_toml(resolved), out=out, strategies=names, resume=resume,
                     step_seconds=step_seconds, connect_timeout=connect_timeout, on_step=on_step)
        team_.finish()
        team_.close()
    except KeyboardInterrupt:
        raise FedmapError(f"base station stopped; carry on with --resume (its journal is in {run_dir(out)})") from None
    finally:
        session.close()
    console.print(f"mission over in {time.perf_counter() - t0:.1f} s; the base's records are in {run_dir(out)}. "
                  f"Copy each rover's log folder into it, then: fedmap score {run_dir(out)} --out {out}", soft_wrap=True)
