"""What the Flower apps do, without Flower: the rover's map and round, the base station's
ground truth, status file, checkpoints and outputs.

As in Flower's quickstart apps (``task.py`` beside two thin app files), the ClientApp and
ServerApp only move messages; the work is here and in the library
(:func:`fedmap.federation.runner.rover_step` / :func:`~fedmap.federation.runner.base_step`,
:mod:`fedmap.stages`, :mod:`fedmap.evaluation`, :mod:`fedmap.outputs`). Nothing here
imports ``flwr``.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

from fedmap._util import AtomicDir, atomic_write_bytes
from fedmap.config import method_config
from fedmap.errors import FedmapError
from fedmap.federation.codecs import Encoder
from fedmap.federation.runner import FederationResult, apply_downlink, rover_step
from fedmap.flower.checkpoint import BaseState, checkpoints, prune, run_dir, write_checkpoint
from fedmap.flower.settings import RunSettings
from fedmap.maps.grid import GridMap, classes_from_rgb
from fedmap.maps.io import load_map, save_map
from fedmap.maps.sources import TerrainSource, load_truth
from fedmap.nets.model import Weights, build_model, render, save_model, set_weights
from fedmap.outputs import write_metrics, write_outputs
from fedmap.pipeline import PipelineResult, build_local_maps
from fedmap.pipeline import initial_weights as run_initial_weights
from fedmap.stages import global_map

# --------------------------------------------------------------------------- the rover


_MAPS: dict[str, tuple[int, GridMap]] = {}  # node config -> its map, read once per process


def load_local_map(node_config: dict) -> tuple[int, GridMap]:
    """``(partition_id, local map)`` of one rover from its node config.

    ``partition-id`` is required. The map is ``map=<path to a PNG/npy map>``, or the
    built-in generator: ``terrain``, ``size``, ``agents``, ``explore``, ``seed`` give the
    same local maps as ``fedmap demo`` (rover ``partition-id`` takes the k-th of them).
    A process reads a given node config's map once (the warm ClientApp server,
    :mod:`fedmap.flower.warm`, reads it before forking the per-message processes).
    """
    key = json.dumps({k: v for k, v in node_config.items() if k not in ("out", "done-file")}, sort_keys=True,
                     default=str)
    if key not in _MAPS:
        _MAPS[key] = _read_local_map(node_config)
    return _MAPS[key]


def _read_local_map(node_config: dict) -> tuple[int, GridMap]:
    if "partition-id" not in node_config:
        raise FedmapError("node config needs partition-id=<rover index>")
    pid = node_config["partition-id"]
    if isinstance(pid, bool) or not isinstance(pid, int) or pid < 0:
        raise FedmapError(f"partition-id must be an integer >= 0, got {pid!r}")
    if "map" in node_config:
        return pid, load_map(str(node_config["map"]))
    if "terrain" not in node_config:
        raise FedmapError("node config needs map=<path> or terrain=<mars|moon|ice> (with size, agents, explore, seed)")
    keys = (("size", "size"), ("agents", "agents"), ("mode", "explore"), ("seed", "seed"))
    given: dict[str, Any] = {k: node_config.get(key) for k, key in keys}
    cfg = method_config(terrain=str(node_config["terrain"]), **given)  # unset: the run config's defaults
    if pid >= cfg.explore.agents:
        raise FedmapError(f"partition-id {pid} is not below agents={cfg.explore.agents}")
    return pid, build_local_maps(cfg, load_truth(cfg.terrain, seed=cfg.seed))[pid]


def initial_weights(settings: RunSettings, height: int) -> Weights:
    """The initial model every rover and the base rebuild alone (never sent)."""
    return run_initial_weights(settings.pipeline, height)


def rover_state(settings: RunSettings, local: GridMap, held: Weights | None,
                encoder: Encoder | None) -> tuple[Weights, Encoder]:
    """What a rover holds before a message: what it kept from its last round, or (first
    message, or its state is gone after a restart) the initial model and a fresh encoder."""
    if held is None or encoder is None:
        return initial_weights(settings, local.shape[0]), Encoder(settings.federation.uplink)
    return held, encoder


def receive(held: Weights, downlink: bytes, kind: str, reference: str) -> Weights:
    """What a rover holds once the downlink arrived (:func:`~fedmap.federation.runner.apply_downlink`):
    raises :class:`~fedmap.errors.RejectedUpdate` for a broadcast relative to a model it does not hold."""
    return apply_downlink(held, kind, downlink, reference)


def train_round(settings: RunSettings, local: GridMap, pid: int, server_round: int, held: Weights,
                encoder: Encoder) -> tuple[bytes, float | None]:
    """One rover's round (:func:`~fedmap.federation.runner.rover_step`): the uplink payload
    and the last loss; raises :class:`~fedmap.errors.RejectedUpdate` when this rover's
    update must be left out."""
    model = build_model(settings.pipeline.model.network(local.shape[0]))
    return rover_step(model, local, held, encoder, settings.federation, round_idx=server_round - 1, agent=pid)


def save_received(settings: RunSettings, local: GridMap, held: Weights, out: Path) -> None:
    """The final global model a rover received, and its rendering, in ``out``."""
    model = build_model(settings.pipeline.model.network(local.shape[0]))
    set_weights(model, held)
    save_model(model, out / "global_model.safetensors")
    rgb = render(model, *local.shape)
    save_map(local.with_classes(classes_from_rgb(rgb), "global map received by the rover"), out / "global_map.png")


# --------------------------------------------------------------------------- the base station


#: The config key of a base's message that names the rover a node's registered key is for (-1: none).
KEY_ROVER = "key-rover"


def wrong_key(node: int, key_rover: int, claimed: int) -> str:
    """The base's line for a node whose key is rover ``key_rover``'s and that says it is ``claimed``."""
    return (f"node {node} holds rover {key_rover}'s registered key but says it is rover {claimed}: refused "
            f"(a rover's key is its number)")


def rover_nodes_text(nodes: dict[int, int]) -> str:
    """``{node: rover}`` as the run config carries it: ``"node=rover,..."`` (\"\": no binding)."""
    return ",".join(f"{n}={k}" for n, k in sorted(nodes.items()))


def parse_rover_nodes(text: str) -> dict[int, int]:
    """The inverse of :func:`rover_nodes_text`."""
    out: dict[int, int] = {}
    for part in filter(None, str(text).split(",")):
        n, _, k = part.partition("=")
        out[int(n)] = int(k)
    return out


def check_key(node_config: dict, key_rover: object) -> None:
    """A rover told by the base that its registered key is rover ``key_rover``'s (-1 or
    None: the base binds no number to it) refuses to run as any other: one line, also
    written to the node config's ``refused-file`` (``fedmap rover`` ends with it)."""
    pid = node_config.get("partition-id")
    if key_rover is None or isinstance(key_rover, bool) or not isinstance(key_rover, int) or key_rover < 0 \
            or key_rover == pid:
        return
    line = (f"rover {pid}: the base station registered this rover's key as rover {key_rover}'s: start it with "
            f"--partition-id {key_rover}, or with its own key (--auth-key DIR/rover{pid})")
    refused = node_config.get("refused-file")
    if refused:
        atomic_write_bytes(Path(str(refused)), line.encode())
    raise FedmapError(line)


def run_status_path(out: Path) -> Path:
    """``<out>.run/status.json``: ``{"state": "running" | "done" | "failed", ...}``."""
    return run_dir(out) / "status.json"


def write_status(out_dir: Path, state: str, **fields: Any) -> None:
    atomic_write_bytes(run_status_path(out_dir), json.dumps({"state": state, **fields}).encode())


def save_checkpoint(settings: RunSettings, state: BaseState) -> None:
    """The base station after ``state.round`` rounds, atomically, in ``<out>.run/``
    (:mod:`fedmap.flower.checkpoint`); only the last ``keep-checkpoints`` are kept."""
    model = build_model(settings.pipeline.model.network(state.shape[0]))
    set_weights(model, state.held)
    tmp = run_dir(settings.out) / f".model-round{state.round}.safetensors"
    save_model(model, tmp, extra={"round": state.round})
    try:
        write_checkpoint(run_dir(settings.out), state, model_bytes=tmp.read_bytes())
    finally:
        tmp.unlink(missing_ok=True)
    prune(run_dir(settings.out), settings.base.keep_checkpoints)
    write_status(settings.out, "running", round=state.round, saved=True)


def truth_shape(settings: RunSettings) -> tuple[int, int] | None:
    """The team's map size when the base has a ground truth (its file's, or the built-in
    terrain's side), else None."""
    if settings.base.truth:
        return base_truth(settings).shape  # type: ignore[union-attr]
    if settings.base.terrain:
        return (settings.base.size, settings.base.size)
    return None


def base_truth(settings: RunSettings) -> GridMap | None:
    """The ground truth the base evaluates against: a map file, a built-in terrain, or None."""
    p = settings.pipeline
    if settings.base.truth:
        return load_truth(TerrainSource(kind="map", path=settings.base.truth))
    if settings.base.terrain:
        return load_truth(p.terrain, seed=p.seed)
    return None


def write_base_outputs(fed: FederationResult, shape: tuple[int, int], settings: RunSettings, flower: dict,
                       *, federation_s: float) -> Path:
    """The demo's output folder (plus per-round checkpoints and the byte ledger)."""
    p = settings.pipeline
    h, w = shape
    t = time.perf_counter()
    net = p.model.network(h)
    model, rgb, classes, refined = global_map(net, fed.weights, (h, w), p.refine)
    truth = base_truth(settings)
    out = settings.out
    if truth is not None:
        if truth.shape != (h, w):
            raise FedmapError(f"the ground truth is {truth.shape}, the rovers' maps are {(h, w)}")
        result = PipelineResult(p, truth, [], model, rgb, classes, refined, fed, p.score(truth, classes),
                                p.score(truth, refined), [],
                                timings={"federation_s": federation_s, "evaluate_s": time.perf_counter() - t})
        write_outputs(result, out, extra_metrics={"flower": flower})
    else:
        frame = GridMap(classes, 1.0, "federated global map")
        metrics = {"aggregator": fed.aggregator, "bytes": fed.total_bytes(), "ledger": fed.ledger(),
                   "rounds": fed.history, "flower": flower}
        with AtomicDir(out) as tmp:
            write_metrics(tmp, {**metrics, "timings": {"federation_s": federation_s}})
            save_model(model, tmp / "global_model.safetensors", extra={"flower": flower["settings"]})
            save_map(frame, tmp / "global_map.png")
            save_map(frame.with_classes(refined, "refined global map"), tmp / "refined_map.png")
    for r, ckpt in checkpoints(run_dir(out)):  # the kept rounds' models go beside the outputs
        if (ckpt / "global_model.safetensors").is_file():
            atomic_write_bytes(out / f"global_model_round{r}.safetensors", (ckpt / "global_model.safetensors").read_bytes())
    write_status(out, "done", rounds=len(fed.history), out=str(out))
    return out
