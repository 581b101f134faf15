"""``fedmap federate-predictor``: the map predictor fine-tuned across sites with FedAvg,
measured on a site held out of training (:mod:`fedmap.training.predictorfed`)."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Optional

import typer

from fedmap._util import make_dir
from fedmap.cli.ui import console
from fedmap.errors import FedmapError
from fedmap.mission import load_mission, mission_terrain
from fedmap.nets.predictor import load_predictor, save_predictor, shipped_predictor
from fedmap.training.predictorfed import (
    FineTuning,
    Site,
    SiteMaps,
    compare,
    federate,
    plot_rounds,
    predictor_from_weights,
    predictor_weights,
    save_site_samples,
    site_maps,
)


def _spec(spec: str) -> tuple[str, Path]:
    """``[NAME=]MISSION.toml`` -> the site's name and its mission file (which must exist)."""
    name, _, path = spec.rpartition("=")
    p = Path(path)
    if not p.is_file():
        raise FedmapError(f"no such mission file: {p} (a site is [NAME=]MISSION.toml)")
    return name or p.stem.removeprefix("mission_"), p


def _site(spec: str, *, steps: int, seed: int) -> SiteMaps:
    """``[NAME=]MISSION.toml`` -> the maps of a raw mission of that mission file on its terrain."""
    name, p = _spec(spec)
    config, source, _ = load_mission(p, seed=seed, mission={"steps": steps, "strategies": ["raw"]})
    truth, elevation, _, profiles = mission_terrain(config, source)
    return site_maps(config, truth, name=name, every=10, elevation=elevation, profiles=profiles,
                     thresholds=source.thresholds)


def federate_predictor(
    sites: list[str] = typer.Argument(..., help="The training sites: [NAME=]MISSION.toml each (a mission's base "
                                      "station and its terrain; NAME defaults to the file's name)."),
    held_out: str = typer.Option(..., "--held-out", help="[NAME=]MISSION.toml of the site held out of training "
                                 "(scored on its cells nobody observed)."),
    rounds: int = typer.Option(5, help="FedAvg rounds."),
    local_steps: int = typer.Option(40, "--local-steps", help="Adam steps of each site per round (pooled and each "
                                    "site alone: as many per round)."),
    batch: int = typer.Option(8, help="Maps per Adam step."),
    crop: int = typer.Option(96, help="Side of the random crop of every map, cells."),
    lr: float = typer.Option(5e-4, help="Adam learning rate (constant)."),
    steps: int = typer.Option(200, help="Steps of the raw mission run on every site."),
    held_out_seeds: int = typer.Option(2, "--held-out-seeds", help="Missions (seeds 0..N-1) scored on the held-out "
                                       "site."),
    init: Optional[Path] = typer.Option(None, "--init", help="Weights to start from (default: the shipped predictor)."),
    seed: int = typer.Option(0, min=0),
    deploy: Optional[str] = typer.Option(None, "--deploy", help="local: the federated rounds on real processes with "
                                         "Flower (a SuperLink and one SuperNode per site on this machine, each "
                                         "holding only its own samples); default: in process."),
    out: Path = typer.Option(Path("fedmap-out/predictor-federated"), "--out", "-o", help="Output folder."),
) -> None:
    """Fine-tune the map predictor across sites with FedAvg; compare it on a held-out site with pooled training, the offline model and each site alone (JSON and a PNG of accuracy per round)."""
    if deploy not in (None, "local"):
        raise FedmapError(f"unknown --deploy {deploy!r}: only local")
    if held_out_seeds < 1:
        raise FedmapError(f"--held-out-seeds must be >= 1, got {held_out_seeds}")
    training = FineTuning(steps=local_steps, batch=batch, crop=crop, lr=lr, seed=seed)
    if rounds < 1:
        raise FedmapError(f"--rounds must be >= 1, got {rounds}")
    # the cheap checks before the sites' missions run
    names = [_spec(spec)[0] for spec in sites]
    if len(set(names)) != len(names):
        raise FedmapError(f"two sites share a name: {names}; name them NAME=MISSION.toml")
    held_name = _spec(held_out)[0]
    if held_name in names:
        raise FedmapError(f"the held-out site {held_name} is also a training site")
    init_weights = predictor_weights(load_predictor(init) if init else shipped_predictor())
    make_dir(out)
    t0 = time.perf_counter()
    train = []
    for spec in sites:
        maps = _site(spec, steps=steps, seed=0)
        train.append(Site.of(maps))
        console.print(f"site {maps.name}: {len(maps)} maps; its final map knows {(maps.final != 2).mean():.0%} "
                      "of the cells")
    held = _site(held_out, steps=steps, seed=0)
    for s in range(1, held_out_seeds):
        held = held.join(_site(held_out, steps=steps, seed=s))
    if deploy is None:
        console.print("training: federated (in process)")
        federated = federate(init_weights, train, training, rounds)
    else:
        from fedmap.flower.predictor.deploy import deploy_predictor

        files = [save_site_samples(out / "sites" / f"{s.name}.npz", s.beliefs, s.targets) for s in train]
        run_config = {"local-steps": local_steps, "batch": batch, "crop": crop, "lr": lr, "seed": seed,
                      "init": str(Path(init).resolve()) if init else ""}
        federated = deploy_predictor(files, out=out / "flower", rounds=rounds, run_config=run_config,
                                     on_status=lambda st: console.print(f"flower: {st.get('state')} round "
                                                                        f"{st.get('round', 0)}"))
    result = compare(init_weights, train, held, training, rounds, federated=federated,
                     on_progress=lambda what: console.print(f"training: {what}"))
    result.update(deploy=deploy or "in-process", mission_steps=steps, seconds=time.perf_counter() - t0)
    if deploy == "local":  # the rounds on Flower: seconds and bytes each way (fp32 payloads)
        from fedmap.flower.predictor.task import read_rounds_log

        result["flower"] = read_rounds_log(out / "flower")
    (out / "federated.json").write_text(json.dumps(result, indent=1))
    plot_rounds([result], out / "rounds.png")
    save_predictor(predictor_from_weights(federated[-1]), out / "federated.safetensors",
                   extra={"sites": names, "rounds": rounds, "training": result["training"]})
    console.print(f"held out {held.name}, {result['final']['offline']['cells']:,} cells nobody observed:")
    for name, s in result["final"].items():
        console.print(f"  {name:<22} accuracy {s['accuracy']:.3f}  IoU {s['iou_impassable']:.3f}  "
                      f"Brier {s['brier']:.3f}  ECE {s['ece']:.3f}")
    console.print(f"federated - pooled {100 * result['federated_minus_pooled']:+.1f} points, federated - offline "
                  f"{100 * result['federated_minus_offline']:+.1f} points; {out}/federated.json, rounds.png  "
                  f"wall time {time.perf_counter() - t0:.1f} s")
