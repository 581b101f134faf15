"""``fedmap base-station`` / ``rover`` / ``certs``: real federation with Flower (:mod:`fedmap.flower`).

Nothing here imports ``flwr``: the commands start Flower's own processes
(:mod:`fedmap.flower.launch`), which load fedmap's ClientApp and ServerApp.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Optional

import typer

from fedmap import _schema
from fedmap._util import check_output_dir
from fedmap.cli.options import parameters, with_settings
from fedmap.cli.ui import console, progress_bar
from fedmap.config import resolve
from fedmap.explore import ExploreConfig
from fedmap.flower.checkpoint import resume_config
from fedmap.flower.launch import make_certs, run_base_station
from fedmap.flower.rover import ROVER_MAX_WAIT, rover_node_config, run_rover
from fedmap.flower.settings import BaseStation, RunSettings, flower_key, run_config_from
from fedmap.maps.sources import DEFAULT_BUILTIN_SIZE
from fedmap.pipeline import PipelineConfig

#: ``base-station``'s generated options: the run settings the base station passes on (no
#: [terrain]: it names its ground truth with its own settings) and its own settings.
_SETTINGS = [*(s for s in _schema.walk(PipelineConfig) if s.section not in ("terrain", "thresholds")),
             *_schema.settings(BaseStation)]
_BASE = {s.name for s in _schema.settings(BaseStation)}


@with_settings(parameters(_SETTINGS, presets=True, skip=("--out", "--resume")))
def base_station(
    host: str = typer.Option("0.0.0.0", help="Address the SuperLink listens on."),
    port: int = typer.Option(9092, help="SuperLink port (rovers connect to HOST:PORT)."),
    certs: Optional[Path] = typer.Option(None, help="TLS: folder from `fedmap certs` (ca.crt, server.pem, server.key)."),
    auth_keys: Optional[Path] = typer.Option(None, "--auth-keys", help="SuperNode authentication: folder of rover *.pub keys."),
    insecure: bool = typer.Option(False, "--insecure", help="Listen beyond this machine without TLS or rover authentication (a trusted network only; loopback needs no flag)."),
    out: Path = typer.Option(Path("fedmap-out/flower"), "--out", "-o", help="Output folder (replaced atomically)."),
    resume: Optional[Path] = typer.Option(None, "--resume", metavar="OUT",
                                          help="Continue the crashed run that was writing to OUT from its last "
                                               "complete checkpoint (its settings; the run options are ignored)."),
    settings: Optional[dict] = None,
) -> None:
    """Base station: start a SuperLink and run fedmap's ServerApp for R rounds."""
    settings = dict(settings or {})
    base = {k: settings.pop(k) for k in list(settings) if k in _BASE}
    cfg = run_config_from(resolve(None, [settings]), **base, out=str(out))
    if resume is not None:
        cfg, out = resume_config(resume), resume
        if "keep_checkpoints" in base:
            cfg[flower_key("keep_checkpoints")] = base["keep_checkpoints"]
        console.print(f"resuming {out} from {Path(cfg['resume']).name}")
    check_output_dir(out)  # before the SuperLink starts: a folder that is not fedmap's, or cannot be written
    rounds = RunSettings.from_run_config(cfg).federation.rounds
    t0 = time.perf_counter()
    with progress_bar() as progress:
        task = progress.add_task("waiting for rovers", total=rounds, loss="")

        def on_status(st: dict) -> None:
            done = st.get("round", 0) - (0 if st.get("saved") or st["state"] == "done" else 1)
            what = "finished" if st["state"] == "done" else f"round {st.get('round', 0)}/{rounds}"
            progress.update(task, completed=min(rounds, done), description=what,
                            loss=f"{st.get('nodes', '')} rovers" if "nodes" in st else "")

        def on_ready() -> None:
            console.print(f"ready: SuperLink on {host}:{port} ({'TLS' if certs else 'insecure'}"
                          f"{', SuperNode auth' if auth_keys else ''}); start the rovers with: "
                          f"fedmap rover --superlink <this host>:{port} --partition-id K ...")

        run_base_station(cfg, host=host, port=port, certs=certs, auth_keys=auth_keys, on_status=on_status,
                         on_ready=on_ready, insecure=insecure)
    m = json.loads((out / "metrics.json").read_text())
    for r in m["rounds"]:
        console.print(f"round {r['round']}: aggregated rovers {sorted(int(k) for k in r['aggregation_counts'])}; "
                      f"missing {r['missing'] or 'none'}; dropped {r['dropped'] or 'none'}; "
                      f"uplink {sum(r['uplink_bytes'].values()):,} B")
    if "global" in m:
        console.print(f"global map: PSNR {_db(m['global']['psnr'])}, path F1 {m['global']['path']['f1']:.2f}")
    b = m["bytes"]
    console.print(f"link: {b['uplink']:,} B uplink, {b['downlink']:,} B downlink; "
                  f"{b['uplink_per_agent_round']:,.0f} B per rover per round uplink")
    console.print(f"outputs: {out}/  (metrics.json, global_model*.safetensors, maps); "
                  f"wall time {time.perf_counter() - t0:.1f} s")

def _db(psnr: float | None) -> str:
    """PSNR as metrics.json stores it: an exact map's infinite PSNR is ``null``."""
    return "inf dB (exact)" if psnr is None else f"{psnr:.2f} dB"


def rover(
    superlink: str = typer.Option(..., help="The base station's SuperLink as HOST:PORT."),
    partition_id: int = typer.Option(..., "--partition-id", help="This rover's index in the team (0-based)."),
    map_path: Optional[Path] = typer.Option(None, "--map", help="This rover's local map (.png or .npy)."),
    terrain: Optional[str] = typer.Option(None, help="Or: take the local map from the built-in generator (mars, moon, ice)."),
    size: int = typer.Option(DEFAULT_BUILTIN_SIZE, help="Generator: map side in cells."),
    agents: int = typer.Option(ExploreConfig().agents, help="Generator: rovers in the team."),
    explore: str = typer.Option(ExploreConfig().mode, help="Generator: exploration pattern."),
    seed: int = typer.Option(0, min=0, help="Generator: seed (the same as the base station's)."),
    root_cert: Optional[Path] = typer.Option(None, "--root-cert", help="TLS: the base station's ca.crt (else insecure)."),
    auth_key: Optional[Path] = typer.Option(None, "--auth-key", help="SuperNode authentication: this rover's private key."),
    port: int = typer.Option(0, help="Local port of the SuperNode's own API (0: any free port)."),
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="Save the final global model and map here."),
    max_wait: float = typer.Option(ROVER_MAX_WAIT, "--max-wait",
                                   help="Seconds to keep trying to reach the SuperLink before giving up."),
    fault: Optional[str] = typer.Option(None, hidden=True, help="Testing: inject a fault (bitflip@R, nan@R)."),
    log: Optional[Path] = typer.Option(None, "--log",
                                       help="Append the Flower SuperNode's log here (default: a temporary file, "
                                            "removed when the rover exits)."),
    warm: bool = typer.Option(True, "--warm/--cold",
                              help="Fork each message's ClientApp from one process that imported torch and "
                                   "fedmap once (--cold: a fresh process per message, Flower's default)."),
    poll: Optional[float] = typer.Option(None, "--poll", min=0.01, help="Seconds between the SuperNode's polls of the SuperLink when idle (default: Flower's 3 s; a mission's rounds come every sync: 0.1 on a fast link)."),
    heartbeat: Optional[float] = typer.Option(None, "--heartbeat", help="Seconds between the SuperNode's heartbeats, 10-1800 (default: Flower's 30). The base station takes a rover for gone after two missed ones: a dead rover holds up a round, and a restarted one is refused as still connected, for twice this."),
    state: Optional[Path] = typer.Option(None, "--state", help="--mission: the folder the rover keeps its state in between messages (a restarted rover carries on from it; default: a temporary folder)."),
    rejoin: bool = typer.Option(False, "--rejoin", help="This rover was restarted: its key was accepted before, so a refusal may be the SuperLink still listing its old node; keep trying."),
    feed: Optional[Path] = typer.Option(None, "--feed", help="--mission: take this rover's observations from its own mapping software: a folder of map snapshots named with their step (map_0040.png, GeoTIFF, ...) or a ROS 2 bag of nav_msgs/OccupancyGrid."),
    feed_topic: Optional[str] = typer.Option(None, "--feed-topic", help="--feed: the bag's OccupancyGrid topic (default: its only one)."),
    mission: bool = typer.Option(False, "--mission", help="A rover of a mission on processes (fedmap mission --deploy base): it drives, senses and shares on the base station's mission; no --map or --terrain."),
) -> None:
    """Rover: run a Flower SuperNode (a snapshot federation on its local map, or with --mission a rover of a mission); exits when its run ends."""
    cfg = rover_node_config(partition_id=partition_id, map_path=map_path, terrain=terrain, size=size,
                            agents=agents, explore=explore, seed=seed, out=out, fault=fault, mission=mission,
                            state=state, feed=feed, feed_topic=feed_topic)
    if root_cert is None:
        console.print("warning: no --root-cert, connecting without TLS (fine on a trusted local network only)")
    console.print(f"rover {partition_id}: connecting to {superlink}")
    code = run_rover(cfg, superlink=superlink, root_cert=root_cert, auth_key=auth_key, port=port, max_wait=max_wait,
                     warm=warm, log=log, poll=poll, rejoin=rejoin, heartbeat=heartbeat)
    if mission:
        console.print(f"rover {partition_id}: mission over")
        raise typer.Exit(code)
    console.print(f"rover {partition_id}: run finished, final global model received"
                  + (f"; saved in {out}/" if out else ""))
    raise typer.Exit(code)

def certs(
    out_dir: Path = typer.Argument(..., help="Folder for the certificates and keys."),
    host: list[str] = typer.Option(["localhost", "127.0.0.1"], "--host",
                                   help="Name or IP the rovers use to reach the base station (repeat)."),
    rovers: int = typer.Option(4, help="SuperNode authentication key pairs to make (rover0..)."),
    days: int = typer.Option(365, help="Certificate lifetime in days."),
    force: bool = typer.Option(False, "--force", help="Replace the CA and keys already in the folder (every base "
                               "station and rover set up with them must get the new ones)."),
) -> None:
    """TLS certificates for the SuperLink and SuperNode authentication keys for the rovers."""
    files = make_certs(out_dir, hosts=host, rovers=rovers, days=days, overwrite=force)
    console.print(f"{out_dir}: " + ", ".join(f.name for f in files))
    console.print("base station: fedmap base-station --certs DIR --auth-keys DIR; "
                  "rover k: fedmap rover --root-cert DIR/ca.crt --auth-key DIR/roverK ...")
