"""The base station's per-round checkpoints: everything a crashed run needs to continue.

After every round the base writes ``<out>.run/checkpoint_round{r:04d}/`` (:func:`run_dir`) with
:class:`~fedmap._util.AtomicDir` (a hidden temporary folder renamed into place when
complete), so a folder with that name is always complete:

``arrays.npz``        the global model (``held/<name>``), the server optimiser's moments
                      (FedAdam / FedYogi ``m/<name>``, ``v/<name>``), the downlink encoder's
                      error-feedback state (``down/...``); plain arrays, no pickle
``state.json``        round, tensor order, the ledger (round history, each round as
                      :meth:`~fedmap.federation.runner.RoundRecord.to_dict`), the team's map size,
                      the run config, and the SHA-256 of ``arrays.npz``
``global_model.safetensors``  the round's model for people and ``fedmap`` commands

Loading checks the hash too, so a folder damaged after it was written (a disk error, a
copy cut short) is skipped: :func:`latest_checkpoint` returns the newest checkpoint that
verifies. Only the last ``keep`` checkpoints are kept (:func:`prune`).

There is no random-number stream to save: every random draw of a run is seeded by
``(seed, round, rover)`` (:func:`fedmap.federation.runner.agent_seed`), so the round number
restores it. What a checkpoint cannot restore is rover-side state: a resumed run is a new
Flower run, so rovers start with no model (they get a keyframe) and, with an uplink codec
with error feedback, an empty residual. This module does not import ``flwr``.
"""

from __future__ import annotations

import hashlib
import io
import json
import re
import shutil
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from fedmap._util import AtomicDir, to_json
from fedmap.errors import FedmapError
from fedmap.federation.runner import RoundRecord
from fedmap.nets.model import Weights

_NAME = re.compile(r"^checkpoint_round(\d{4,})$")


@dataclass
class BaseState:
    """The base station after ``round`` completed rounds."""

    round: int
    held: Weights
    moments: dict[str, Weights]  # "m" / "v" of FedAdam / FedYogi; empty for FedAvg
    down_encoder: Weights | None  # Encoder.state() of the downlink encoder
    history: list[RoundRecord]
    shape: tuple[int, int]
    run_config: dict[str, Any]


def run_dir(out: Path) -> Path:
    """``<out>.run/``: the base station's status and per-round checkpoints while a run goes."""
    out = Path(out)
    return out.with_name(out.name + ".run")


def checkpoint_dir(run_dir: Path, round_no: int) -> Path:
    return Path(run_dir) / f"checkpoint_round{round_no:04d}"


def write_checkpoint(run_dir: Path, state: BaseState, *, model_bytes: bytes | None = None) -> Path:
    """Write ``state`` as ``checkpoint_round{r}`` in ``run_dir`` (complete or not at all)."""
    arrays: dict[str, np.ndarray] = {f"held/{k}": np.asarray(v) for k, v in state.held.items()}
    for which, weights in state.moments.items():
        arrays.update({f"{which}/{k}": np.asarray(v) for k, v in weights.items()})
    if state.down_encoder is not None:
        arrays.update({f"down/{k}": np.asarray(v) for k, v in state.down_encoder.items()})
    buf = io.BytesIO()
    np.savez(buf, allow_pickle=False, **arrays)
    blob = buf.getvalue()
    meta = {"round": state.round, "names": list(state.held), "moments": sorted(state.moments),
            "history": [r.to_dict() for r in state.history], "shape": list(state.shape), "run_config": state.run_config,
            "arrays_sha256": hashlib.sha256(blob).hexdigest()}
    target = checkpoint_dir(run_dir, state.round)
    with AtomicDir(target) as tmp:
        (tmp / "arrays.npz").write_bytes(blob)
        if model_bytes is not None:
            (tmp / "global_model.safetensors").write_bytes(model_bytes)
        (tmp / "state.json").write_text(to_json(meta))  # last: a folder with it is complete
    return target


def read_checkpoint(path: Path) -> BaseState:
    """A checkpoint folder back as :class:`BaseState`; a damaged one is a one-line error."""
    path = Path(path)
    try:
        meta = json.loads((path / "state.json").read_text())
        blob = (path / "arrays.npz").read_bytes()
    except (OSError, ValueError) as e:
        raise FedmapError(f"checkpoint {path} is incomplete or unreadable ({type(e).__name__})") from None
    if not isinstance(meta, dict) or hashlib.sha256(blob).hexdigest() != meta.get("arrays_sha256"):
        raise FedmapError(f"checkpoint {path} is damaged: arrays.npz does not match its recorded hash")
    try:
        with np.load(io.BytesIO(blob), allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
        names = meta["names"]
        held = {n: arrays[f"held/{n}"] for n in names}  # payload order, as the run had it
        moments = {w: {n: arrays[f"{w}/{n}"] for n in names} for w in meta["moments"]}
        down = {k[len("down/"):]: v for k, v in arrays.items() if k.startswith("down/")} or None
        history = [RoundRecord.from_dict(r) for r in meta["history"]]
        shape = (int(meta["shape"][0]), int(meta["shape"][1]))
        state = BaseState(int(meta["round"]), held, moments, down, history, shape, dict(meta["run_config"]))
    except FedmapError as e:
        raise FedmapError(f"checkpoint {path} is damaged: {e}") from None
    except (KeyError, IndexError, TypeError, ValueError, AttributeError, OSError, EOFError, NotImplementedError,
            zipfile.BadZipFile, zlib.error) as e:
        what = f"missing {e}" if isinstance(e, KeyError) else " ".join(str(e).split()) or type(e).__name__
        raise FedmapError(f"checkpoint {path} is damaged ({type(e).__name__}: {what})") from None
    return state


def checkpoints(run_dir: Path) -> list[tuple[int, Path]]:
    """``(round, folder)`` of the checkpoint folders in ``run_dir``, oldest first (temporary
    folders of an interrupted write are hidden and never listed)."""
    found = []
    for p in Path(run_dir).glob("checkpoint_round*"):
        m = _NAME.match(p.name)
        if m and p.is_dir():
            found.append((int(m.group(1)), p))
    return sorted(found)


def latest_checkpoint(run_dir: Path) -> tuple[Path, BaseState] | None:
    """The newest checkpoint in ``run_dir`` that verifies (its folder and state), or None."""
    for _, p in reversed(checkpoints(run_dir)):
        try:
            return p, read_checkpoint(p)
        except FedmapError:
            continue  # damaged: fall back to the one before
    return None


def resume_config(out: Path) -> dict[str, Any]:
    """The run config that continues the crashed run whose outputs were to go to ``out``:
    its own run config, ``resume`` set to its newest complete checkpoint."""
    found = latest_checkpoint(run_dir(Path(out).resolve()))
    if found is None:
        raise FedmapError(f"nothing to resume: no complete checkpoint in {run_dir(Path(out).resolve())}")
    path, state = found
    return {**state.run_config, "resume": str(path), "out": str(Path(out).resolve())}


def prune(run_dir: Path, keep: int) -> None:
    """Keep the newest ``keep`` checkpoints; remove older ones and leftovers of
    interrupted writes."""
    for _, p in checkpoints(run_dir)[:-keep] if keep > 0 else []:
        shutil.rmtree(p, ignore_errors=True)
    for p in Path(run_dir).glob(".checkpoint_round*.tmp-*"):
        shutil.rmtree(p, ignore_errors=True)
