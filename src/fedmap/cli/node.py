"""``fedmap node rover`` / ``fedmap node peer`` / ``fedmap node base``: one node of a team as
its own process, over Zenoh (:mod:`fedmap.zenohnet`). This module only wires options."""

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
    ros2: bool = typer.Option(False, "--ros2", help="Live in the robot's ROS 2 graph (DDS): the map comes from --map-topic, the team's map goes out on --team-map-topic (latched) and the status on /fedmap/status."),
    domain: Optional[int] = typer.Option(None, "--domain", help="--ros2: the ROS_DOMAIN_ID (default: the environment's, else 0)."),
    map_topic: str = typer.Option("/map", "--map-topic", help="--ros2: the robot's nav_msgs/OccupancyGrid (slam_toolbox, Cartographer, map_server)."),
    team_map_topic: str = typer.Option("/fedmap/team_map", "--team-map-topic", help="--ros2: where the team's map goes (reliable, transient local: Nav2's static layer)."),
    pose_topic: Optional[str] = typer.Option(None, "--pose-topic", help="--ros2: the rover's pose in its map's frame (geometry_msgs/PoseStamped, or nav_msgs/Odometry with --pose-odometry); default: placed by what it observes."),
    pose_odometry: bool = typer.Option(False, "--pose-odometry", help="--pose-topic carries nav_msgs/Odometry."),
    bag: Optional[Path] = typer.Option(None, "--bag", help="--ros2: rehearse from a recorded rover: play this ROS 2 bag's --map-topic (and --pose-topic) into the graph at its own timing."),
    ros2_loopback: bool = typer.Option(False, "--ros2-loopback", help="--ros2: keep DDS on this machine (the loopback interface, no multicast)."),
    first_map: float = typer.Option(0.0, "--first-map", min=0.0, help="--ros2: wait up to this many seconds for the first map on --map-topic (and the first pose on --pose-topic) before joining the team (0: join at once; the rover observes nothing until a map comes)."),
    fault: Optional[str] = typer.Option(None, hidden=True, help="Testing: corrupt@STEP damages one report."),
) -> None:
    """A rover node: answers the base station's orders (drive, sense, share) until the mission is over."""
    from fedmap.mission.world.feed import MapFeed
    from fedmap.zenohnet.rover import serve_rover
    from fedmap.zenohnet.session import node_config, open_session

    ep, tls, folder = _rover_ends(rover_, connect, team, state, certs)
    ros_only = [o for o, on in (("--domain", domain is not None), ("--bag", bag is not None),
                                ("--ros2-loopback", ros2_loopback), ("--first-map", first_map > 0),
                                ("--pose-topic", pose_topic is not None), ("--pose-odometry", pose_odometry)) if on]
    if ros_only and not ros2:
        raise FedmapError(f"{', '.join(ros_only)} apply with --ros2 only")
    if ros2 and feed is not None:
        raise FedmapError("--feed and --ros2 are two sources of the rover's map: give one")

    def say(line: str) -> None:
        console.print(escape(line), soft_wrap=True)

    bridge, player = None, None
    if ros2:
        from fedmap.zenohnet.ros2 import POSE_TYPES, Ros2Bridge, play_in_background

        ros_id = ros_domain(domain)
        bridge = Ros2Bridge(rover_, domain=ros_id, map_topic=map_topic, team_topic=team_map_topic,
                            pose_topic=pose_topic, pose_type=POSE_TYPES[1 if pose_odometry else 0],
                            loopback=ros2_loopback, say=say)
        if bag is not None:
            player = play_in_background(bag, ros_id, [map_topic, *([pose_topic] if pose_topic else [])],
                                        loopback=ros2_loopback, say=say)
        if first_map > 0:
            bridge.wait_first(first_map)
    mapfeed = MapFeed.open(feed, topic=feed_topic) if feed is not None else None
    session = open_session(node_config(connect=[ep], certs=tls))
    try:
        console.print(f"rover {rover_} of team {team}: connecting to {ep}; log in {folder}/log"
                      + (f"; ROS 2 map in {map_topic}, team map out {team_map_topic}" if ros2 else ""), soft_wrap=True)
        n = serve_rover(session, team, rover_, folder, feed=mapfeed, fault=fault, bridge=bridge, say=say)
    except KeyboardInterrupt:
        raise FedmapError(f"rover {rover_} stopped; its log is in {folder}/log") from None
    finally:
        session.close()
    console.print(f"rover {rover_}: mission over ({n} orders answered)")
    if bridge is not None:  # a ROS 2 node stays in its graph: Nav2 and RViz may still join for the team map
        console.print(f"the last team map stays on {team_map_topic} until this node is stopped (Ctrl-C)")
        try:
            while True:
                time.sleep(3600)
        except KeyboardInterrupt:
            console.print(f"rover {rover_}: stopped")
    del player  # (a bag's player keeps its last map latched until here)


def _rover_ends(k: int, connect: str, team: str, state: Optional[Path],
                certs: Optional[Path]) -> tuple[str, Any, Path]:
    """A rover node's endpoint, its TLS files (None without ``certs``) and its state folder, checked."""
    from fedmap.zenohnet.session import Certs, check_team, endpoint

    check_team(team)
    ep = endpoint(connect, tls=certs is not None)
    return ep, Certs.for_node(certs, f"rover{k}") if certs is not None else None, state or Path(f"fedmap-rover{k}")


def ros_domain(domain: Optional[int]) -> int:
    """``--domain``, else ROS_DOMAIN_ID, else 0 (one line for a value DDS refuses)."""
    import os

    from fedmap.maps.ros2dds import check_domain

    if domain is not None:
        return check_domain(domain)
    text = os.environ.get("ROS_DOMAIN_ID", "").strip() or "0"
    if not text.isdigit():
        raise FedmapError(f"ROS_DOMAIN_ID must be a whole number in [0, 232], got {text!r}")
    return check_domain(int(text))


@node_app.command("peer")
def peer(
    rover_: int = typer.Option(..., "--rover", min=0, help="This rover's index in the team (0-based)."),
    connect: str = typer.Option(..., "--connect", help="The lander's HOST:PORT (fedmap node base of a mesh or leader mission)."),
    team: str = typer.Option("fedmap", "--team", help="The team's name (teams can share a network); the lander's --team."),
    state: Optional[Path] = typer.Option(None, "--state", help="Folder for this rover's own log (default: fedmap-rover<k>); the mission is scored from it."),
    certs: Optional[Path] = typer.Option(None, "--certs", help="TLS with mutual authentication: a folder with ca.crt, rover<k>.crt and rover<k>.key (from fedmap certs)."),
    connect_timeout: float = typer.Option(300.0, "--connect-timeout", min=1.0, help="Seconds to wait for the lander and every other agent to come up."),
    fault: Optional[str] = typer.Option(None, hidden=True, help="Testing: corrupt@STEP damages one mail."),
) -> None:
    """A rover of a peer mission (mesh or leader): runs its side of every sync round with the other agents; no orders."""
    from fedmap.zenohnet.peer import serve_peer
    from fedmap.zenohnet.session import node_config, open_session

    ep, tls, folder = _rover_ends(rover_, connect, team, state, certs)
    console.print(f"rover {rover_} of team {team}: peer node, connecting to {ep}", soft_wrap=True)
    # a client of the lander's router (its access control sees every message); waits for it up to --connect-timeout
    session = open_session(node_config(connect=[ep], certs=tls, mode="client", connect_timeout=connect_timeout))
    try:
        names = serve_peer(session, team, rover_, folder, connect_timeout=connect_timeout, fault=fault)
    except KeyboardInterrupt:
        raise FedmapError(f"rover {rover_} stopped") from None
    finally:
        session.close()
    console.print(f"rover {rover_}: ran {', '.join(names)}; its log is in {folder / 'log'}", soft_wrap=True)


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
    """The base station (star) or the lander (mesh, leader): runs the mission's clock or desk, logs its side; score with fedmap score."""
    from fedmap.mission import load_mission
    from fedmap.mission.network.peers import peer_strategies
    from fedmap.mission.network.remote import deployable_strategies
    from fedmap.mission.settings import mission_toml
    from fedmap.zenohnet.base import ZenohTeam, run_base
    from fedmap.zenohnet.session import Certs, acl, check_listen, check_team, endpoint, node_config, open_session

    check_team(team)
    cfg, _source, resolved = load_mission(config, preset=preset, overrides=[*parse_sets(set_)])
    peers = cfg.link.topology != "star"
    if peers and (resume or step_seconds):
        raise FedmapError("a peer mission runs in lockstep from its start: --resume and --step-seconds are for the star")
    names, _ = peer_strategies(cfg) if peers else deployable_strategies(cfg)
    ep = endpoint(listen, tls=certs is not None)
    check_listen([ep], secure=certs is not None, insecure=insecure)
    members = cfg.rovers + cfg.helicopters
    tls = Certs.for_node(certs, "base") if certs is not None else None
    session = open_session(node_config(listen=[ep], certs=tls, access=None if tls is None else acl(team, members),
                                       mode="router" if peers else "peer"))
    if peers:
        _lander(session, cfg, mission_toml(resolved), names, team=team, listen=listen, certs=certs, out=out,
                connect_timeout=connect_timeout)
        return
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


def _lander(session: Any, cfg: Any, text: str, names: tuple[str, ...], *, team: str, listen: str,
            certs: Optional[Path], out: Path, connect_timeout: float) -> None:
    """``fedmap node base`` of a peer mission: the lander (:func:`fedmap.zenohnet.peer.run_lander`)."""
    from fedmap.zenohnet.peer import run_lander

    t0 = time.perf_counter()
    try:
        console.print(f"lander of team {team} ({cfg.link.topology}) listening; start each rover k with: fedmap node "
                      f"peer --rover k --connect {listen}{' --certs DIR' if certs else ''}", soft_wrap=True)
        with progress_bar() as progress:
            tasks: dict[str, Any] = {}

            def on_step(name: str, step: int) -> None:
                if name not in tasks:
                    tasks[name] = progress.add_task(f"peer mission over Zenoh: {name}", total=cfg.steps, loss="")
                progress.update(tasks[name], completed=step)

            run_lander(session, team, text, out=out, strategies=names, connect_timeout=connect_timeout,
                       on_step=on_step)
    except KeyboardInterrupt:
        raise FedmapError("lander stopped: a peer mission cannot resume; start it again") from None
    finally:
        session.close()
    console.print(f"mission over in {time.perf_counter() - t0:.1f} s; the lander's records are in {run_dir(out)}. "
                  f"Copy each rover's log folder into it, then: fedmap score {run_dir(out)} --out {out}", soft_wrap=True)
