"""In-process federation: distribute -> local fit -> encode/send -> aggregate, R rounds.

Every payload really goes through bytes (:mod:`fedmap.federation.codecs`) in both directions and the
models are rebuilt from the decoded bytes, so metrics are computed on what a link
delivers and byte counts are ``len()`` of what it carries.

* **Downlink.** Every rover starts round 1 from the initial model, which all of them
  already hold (it is seeded or shipped with the package), so nothing is sent for it.
  After each aggregation the base broadcasts the new global model with the downlink
  codec, relative to the model the rovers hold (for update/top-k codecs); every rover
  decodes the same bytes, and the base continues from that decoded model too, so base
  and rovers never disagree. The returned weights are that decoded broadcast: what the
  rovers render.
* **Uplink.** Each rover has its own encoder (error-feedback residual and momentum stay
  on the rover) and sends its trained weights relative to the model it started from.
* **Versions and keyframes.** Every model a rover can hold has a version, its content
  hash (:func:`model_version`). A rover reports the version it trained from with every
  update, and the base keeps the version each rover holds (:class:`Broadcaster`): a rover
  that holds the model the last broadcast is relative to gets that broadcast; any other
  (it missed a round, restarted, or is unknown) gets a **keyframe**: the whole current
  global model, exact (:data:`KEYFRAME` codec: fp32 values, zstd-compressed). A rover refuses a broadcast
  relative to a model it does not hold (:func:`apply_downlink`), and the base never
  aggregates an update whose reported version is not the model it holds (:func:`base_step`
  with ``versions``): an update is only ever decoded against the reference it was made from.
* **Dropouts.** An agent whose training diverges, whose update is not finite, whose
  payload does not decode, or whose update is relative to a stale model is *dropped* for
  that round (recorded with the reason); an agent that delivers nothing (absent, no reply,
  its process died) is *missing*. The round aggregates the survivors.
* **Ledger.** One row per (round, agent, direction) with the codec and the bytes.
"""

from __future__ import annotations

import hashlib
import struct
import time
from collections.abc import Callable, Collection, Mapping
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from fedmap._schema import setting, wiring
from fedmap.errors import FedmapError, RejectedUpdate
from fedmap.federation.aggregate import AGGREGATORS, Aggregator, check_server_settings, make_aggregator
from fedmap.federation.codecs import CodecSpec, Encoder, decode
from fedmap.maps.grid import GridMap, check_same_frame
from fedmap.nets.model import NetConfig, Weights, build_model, get_weights, set_weights
from fedmap.nets.training import TrainConfig, fit, release_freed_memory, steps_per_epoch


@dataclass(frozen=True)
class FederationConfig:
    """Rounds, aggregation and payload codecs: the ``[federation]`` section of a run config.

    ``local`` (the ``[train]`` section) and ``seed`` (the run's) are filled by the run
    assembly (:class:`fedmap.pipeline.PipelineConfig`); they are not settings of their own.
    """

    rounds: int = setting(1, help="Communication rounds R")
    aggregator: str = setting("fedavg", help="Server aggregation (coverage: coverage-aware FedAvg)",
                              choices=lambda: tuple(AGGREGATORS))
    eta: float = setting(1e-2, help="Server learning rate (fedadam, fedyogi)")
    beta1: float = setting(0.9, help="Server first-moment decay (fedadam, fedyogi)")
    beta2: float = setting(0.99, help="Server second-moment decay (fedadam, fedyogi)")
    tau: float = setting(1e-3, help="Server adaptivity epsilon (fedadam, fedyogi)")
    local: TrainConfig = wiring(default_factory=TrainConfig)
    seed: int = wiring(0)
    uplink: str = setting("fp32", help="Rover -> base payload codec: fp32, fp16, bf16, int8, int4, topk:0.01, "
                          "update-int4, ... (+zstd)")
    downlink: str = setting("fp32", help="Base -> rover payload codec (the uplink's grammar)")
    versions_kept: int = setting(0, help="Older models the base keeps: a rover behind by up to this many gets the chain "
                          "of broadcasts when cheaper than a keyframe, and its update is applied as a delta (0: "
                          "updates only from the current model)")

    def __post_init__(self) -> None:
        if self.rounds < 1:
            raise FedmapError(f"rounds must be >= 1, got {self.rounds}")
        k = self.versions_kept
        if isinstance(k, bool) or not isinstance(k, int) or not 0 <= k <= 255:
            raise FedmapError(f"versions_kept must be a whole number of models from 0 to 255, got {k!r}")
        CodecSpec.parse(self.uplink)
        CodecSpec.parse(self.downlink)
        check_server_settings("[federation]", eta=self.eta, beta1=self.beta1, beta2=self.beta2, tau=self.tau)
        self.make_aggregator()

    def make_aggregator(self) -> Aggregator:
        """A fresh aggregator of this config (FedAdam / FedYogi with their server state)."""
        return make_aggregator(self.aggregator, eta=self.eta, beta1=self.beta1, beta2=self.beta2, tau=self.tau)

    def to_dict(self) -> dict:
        return asdict(self)


def _by_agent(d: Mapping[Any, Any]) -> dict[int, Any]:
    """A dict keyed by agent (rover index, Flower partition id) back from JSON, where its keys became strings."""
    return {int(k): v for k, v in d.items()}


#: The JSON keys a Flower round adds to :meth:`RoundRecord.to_dict` (:meth:`FlowerRound.to_dict`).
_FLOWER_KEYS = ("missing_why", "node_errors", "flower_uplink_bytes", "flower_downlink_bytes",
                "final_broadcast_received_by", "resent")


@dataclass(frozen=True)
class FlowerRound:
    """What the Flower base station (:mod:`fedmap.flower.snapshot.server`) adds to a round's record.

    ``missing_why``: missing rover -> why it delivered nothing; ``node_errors``: Flower node id
    (a string) -> its error, for nodes that never said which rover they are; ``uplink_bytes`` /
    ``downlink_bytes``: rover -> the bytes Flower counted for its payload (fedmap's payload plus
    the record's ``.npy`` header and key; ``downlink_bytes`` is filled in as the round's model
    reaches the rovers); ``final_broadcast_received_by``: the rovers that acknowledged the
    final model (set on the last round once the run ends, else None); ``resent``: rover -> the
    copies of its train message sent because it went unanswered far longer than the others'
    (:func:`fedmap.flower.polling.exchange`; each crosses the link again).
    """

    missing_why: dict[int, str]
    node_errors: dict[str, str]
    uplink_bytes: dict[int, int]
    downlink_bytes: dict[int, int]
    final_broadcast_received_by: list[int] | None = None
    resent: dict[int, int] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """The JSON keys it adds to its round's :meth:`RoundRecord.to_dict` (``flower_uplink_bytes``, ...)."""
        d: dict[str, Any] = {"missing_why": dict(self.missing_why), "node_errors": dict(self.node_errors),
                             "flower_uplink_bytes": dict(self.uplink_bytes),
                             "flower_downlink_bytes": dict(self.downlink_bytes)}
        if self.final_broadcast_received_by is not None:
            d["final_broadcast_received_by"] = list(self.final_broadcast_received_by)
        if self.resent:
            d["resent"] = dict(self.resent)
        return d

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> FlowerRound:
        """The Flower part of a round record in :meth:`RoundRecord.to_dict` layout (after JSON)."""
        acked = d.get("final_broadcast_received_by")
        return cls(missing_why=_by_agent(d.get("missing_why", {})),
                   node_errors={str(k): v for k, v in d.get("node_errors", {}).items()},
                   uplink_bytes=_by_agent(d.get("flower_uplink_bytes", {})),
                   downlink_bytes=_by_agent(d.get("flower_downlink_bytes", {})),
                   final_broadcast_received_by=None if acked is None else [int(k) for k in acked],
                   resent=_by_agent(d.get("resent", {})))


@dataclass(frozen=True)
class RoundRecord:
    """One round of a federation: an entry of :attr:`FederationResult.history`, the same for
    every runner (in process, Flower). Agents are rover indices (Flower: partition ids).

    Attributes
    ----------
    round : int
        The round number, 1-based.
    final_loss : dict
        Agent -> its last local training loss (None when it took no step), for every
        aggregated agent.
    aggregation_counts : dict
        Agent -> its aggregation count n_k (the known cells of its map: the weight of its
        update in the aggregation), for every agent whose update was aggregated.
    dropped : dict
        Agent -> why its reply was not used (it replied, unlike a missing agent).
    missing : list
        Agents that delivered nothing this round.
    uplink_codec, downlink_codec : str
        The labels of the round's payload codecs.
    uplink_bytes : dict
        Agent -> bytes of its uplink payload.
    downlink_bytes : dict
        Agent -> bytes of this round's model as it was sent to that agent (the broadcast or
        a keyframe).
    keyframes : list
        Agents that got this round's model as a keyframe instead of the broadcast.
    seconds : float
        Wall time of the round.
    flower : FlowerRound or None
        What the Flower base station adds (None in process).

    The record is frozen, but this round's model is sent after the round: ``downlink_bytes``,
    ``keyframes`` and ``flower.downlink_bytes`` are filled in as it reaches the rovers
    (:func:`book_downlink`, in the next round or at the end of the run).

    :meth:`to_dict` is its JSON layout (``metrics.json`` ``rounds``, checkpoints), whose keys
    are not all the field names: the codecs are
    ``codecs: {uplink, downlink}`` and the Flower fields are flat (:meth:`FlowerRound.to_dict`).
    """

    round: int
    final_loss: dict[int, float | None]
    aggregation_counts: dict[int, float]
    dropped: dict[int, str]
    missing: list[int]
    uplink_codec: str
    downlink_codec: str
    uplink_bytes: dict[int, int]
    downlink_bytes: dict[int, int]
    keyframes: list[int]
    seconds: float
    flower: FlowerRound | None = None

    def to_dict(self) -> dict[str, Any]:
        """The record as ``metrics.json`` and checkpoints hold it (int agent keys: ``to_json`` makes them strings)."""
        d: dict[str, Any] = {
            "round": self.round, "final_loss": dict(self.final_loss), "aggregation_counts": dict(self.aggregation_counts),
            "dropped": dict(self.dropped), "missing": list(self.missing),
            "codecs": {"uplink": self.uplink_codec, "downlink": self.downlink_codec},
            "uplink_bytes": dict(self.uplink_bytes), "downlink_bytes": dict(self.downlink_bytes),
            "keyframes": list(self.keyframes), "seconds": self.seconds,
        }
        if self.flower is not None:
            d.update(self.flower.to_dict())
        return d

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> RoundRecord:
        """A record back from :meth:`to_dict`'s layout after JSON (a checkpoint's
        ``state.json``, also one written before records were typed): agent ids are ints again."""
        codecs = d["codecs"]
        counts = d["aggregation_counts"] if "aggregation_counts" in d else d["weights"]  # its name before typed records
        return cls(round=int(d["round"]), final_loss=_by_agent(d["final_loss"]),
                   aggregation_counts=_by_agent(counts), dropped=_by_agent(d["dropped"]),
                   missing=[int(k) for k in d["missing"]], uplink_codec=str(codecs["uplink"]),
                   downlink_codec=str(codecs["downlink"]), uplink_bytes=_by_agent(d["uplink_bytes"]),
                   downlink_bytes=_by_agent(d["downlink_bytes"]), keyframes=[int(k) for k in d.get("keyframes", [])],
                   seconds=float(d["seconds"]),
                   flower=FlowerRound.from_dict(d) if any(k in d for k in _FLOWER_KEYS) else None)


@dataclass
class FederationResult:
    weights: Weights
    history: list[RoundRecord]
    aggregator: dict

    def ledger(self) -> list[dict]:
        """One row per (round, agent, direction): codec and bytes."""
        rows = []
        for r in self.history:
            for direction, sent, codec in (("downlink", r.downlink_bytes, r.downlink_codec),
                                           ("uplink", r.uplink_bytes, r.uplink_codec)):
                for agent, n in sent.items():
                    keyframe = direction == "downlink" and agent in r.keyframes
                    rows.append({"round": r.round, "agent": agent, "direction": direction,
                                 "codec": f"{KEYFRAME} keyframe" if keyframe else codec, "bytes": n})
        return rows

    def total_bytes(self) -> ByteTotals:
        up = sum(sum(r.uplink_bytes.values()) for r in self.history)
        down = sum(sum(r.downlink_bytes.values()) for r in self.history)
        n_up = sum(len(r.uplink_bytes) for r in self.history)
        return ByteTotals(up, down, up / max(n_up, 1))


@dataclass(frozen=True)
class ByteTotals:
    """Bytes on the link over a whole federation (every rover, every round)."""

    uplink: int  # rover -> base, all rovers and rounds
    downlink: int  # base -> rover, all rovers and rounds (broadcasts and keyframes)
    uplink_per_agent_round: float  # mean uplink payload of one rover in one round

    def to_dict(self) -> dict:
        return asdict(self)


def agent_seed(seed: int, round_idx: int, agent: int) -> int:
    """Independent, reproducible seed per (run, round, agent)."""
    return int(np.random.SeedSequence([seed, round_idx, agent]).generate_state(1)[0])


#: The codec of a keyframe: the whole global model, exact, decodable without a reference.
#: fp32 compressed losslessly: GridNet's untouched grid cells compress to almost nothing
#: (a 128² GridNet: 328 kB dense, 31-50 kB here after a Hadley mission's first 60 steps).
KEYFRAME = "fp32+zstd"


def model_version(weights: Weights) -> str:
    """The version of a model: a content hash of its tensors (names, dtypes, shapes, bytes).

    Two models have the same version exactly when they are bit-identical, so a rover and the
    base agree on what a rover holds without sending the model. 16 hex digits (64 bits).
    """
    h = hashlib.sha256()
    for name in sorted(weights):
        a = np.ascontiguousarray(weights[name])
        h.update(f"{name}|{a.dtype.str}|{a.shape}|".encode())
        h.update(a.tobytes())
    return h.hexdigest()[:16]


@dataclass(frozen=True)
class Downlink:
    """What the base sends one rover before a round.

    ``kind`` is ``"none"`` (the rover already holds the current model, or round 1 where every
    rover rebuilds the initial model), ``"broadcast"`` (the round's payload, relative to the
    model of version ``reference``), ``"chain"`` (the broadcasts from the model of version
    ``reference`` to the current one, in order: :func:`pack_chain`) or ``"keyframe"`` (the
    whole current model).
    """

    kind: str
    payload: bytes
    reference: str = ""


class Broadcaster:
    """The base station's downlink: the current global model, the last broadcast and what it
    is relative to, and the keyframe for rovers that hold anything else.

    With a ``window`` of W >= 1 older models, the base keeps the last W models and the
    broadcasts between them: a rover that holds any of them gets the chain of broadcasts to
    the current model when that is smaller than a keyframe, and :func:`base_step` (given
    :attr:`window`) applies an update made from any of them as a delta. ``window=0`` (the
    default) is the protocol without a window: the broadcast for a rover that holds the
    previous model, a keyframe for any other, updates only from the current model.

    Parameters
    ----------
    held : Weights or None
        The model every rover starts from (None when the base does not know it yet: then
        round 1 sends nothing and the rovers' reported versions are checked once it is known).
    window : int
        Older models kept (see above).
    """

    def __init__(self, held: Weights | None, *, window: int = 0) -> None:
        if isinstance(window, bool) or not isinstance(window, int) or window < 0:
            raise FedmapError(f"the version window must be a whole number >= 0, got {window!r}")
        self.keep = max(window, 1)
        self.windowed = window > 0
        self.held: Weights | None = None
        self.version = ""
        #: the last broadcasts, oldest first: (version it decodes against, that model, payload)
        self.past: list[tuple[str, Weights, bytes]] = []
        self._keyframe: bytes | None = None
        if held is not None:
            self.reset(held)

    @property
    def window(self) -> dict[str, Weights]:
        """The older models an update may be made from (version -> weights; empty without a window)."""
        return {v: w for v, w, _ in self.past} if self.windowed else {}

    def reset(self, held: Weights) -> None:
        """Hold ``held`` with no broadcast to build on (start, or resume from a checkpoint):
        every rover that does not hold exactly ``held`` gets a keyframe."""
        self.held, self.version = held, model_version(held)
        self.past, self._keyframe = [], None

    def advance(self, held: Weights, payload: bytes) -> None:
        """The round's broadcast ``payload`` (relative to the model held so far) decodes to ``held``."""
        assert self.held is not None
        self.past = [*self.past, (self.version, self.held, payload)][-self.keep:]
        self.held, self.version, self._keyframe = held, model_version(held), None

    def keyframe(self) -> bytes:
        """The whole current model (:data:`KEYFRAME` codec)."""
        assert self.held is not None
        if self._keyframe is None:
            self._keyframe = Encoder(KEYFRAME).encode(self.held)
        return self._keyframe

    def for_rover(self, version: str | None) -> Downlink:
        """What a rover that holds model ``version`` (None: unknown) must be sent."""
        if self.held is None or version == self.version:
            return Downlink("none", b"")
        refs = [v for v, _, _ in self.past]
        if version in refs:
            i = refs.index(version)
            if i == len(refs) - 1:
                return Downlink("broadcast", self.past[-1][2], version)
            chain = pack_chain([p for _, _, p in self.past[i:]])
            if len(chain) < len(self.keyframe()):
                return Downlink("chain", chain, version)
        return Downlink("keyframe", self.keyframe())


_CHAIN = struct.Struct("<4sB")
_CHAIN_MAGIC = b"FMCH"


def pack_chain(payloads: list[bytes]) -> bytes:
    """Broadcasts to apply in order, as one payload: magic, count, then each length (u32) and payload."""
    if not 1 <= len(payloads) <= 255:
        raise FedmapError(f"a chain holds 1 to 255 broadcasts, not {len(payloads)}")
    return _CHAIN.pack(_CHAIN_MAGIC, len(payloads)) + b"".join(struct.pack("<I", len(p)) + p for p in payloads)


def unpack_chain(data: bytes) -> list[bytes]:
    """The broadcasts of a :func:`pack_chain` payload (one-line RejectedUpdate when malformed)."""
    buf = bytes(data)
    if len(buf) < _CHAIN.size or buf[:4] != _CHAIN_MAGIC:
        raise RejectedUpdate("malformed chain: bad magic or too short")
    n, off, out = buf[4], _CHAIN.size, []
    for _ in range(n):
        if off + 4 > len(buf):
            raise RejectedUpdate("malformed chain: truncated")
        (length,) = struct.unpack_from("<I", buf, off)
        if off + 4 + length > len(buf):
            raise RejectedUpdate("malformed chain: truncated")
        out.append(buf[off + 4:off + 4 + length])
        off += 4 + length
    if off != len(buf) or not out:
        raise RejectedUpdate("malformed chain: bytes after its last broadcast, or none")
    return out


def apply_downlink(held: Weights, kind: str, payload: bytes, reference: str = "") -> Weights:
    """The rover's side of :class:`Downlink`: the model it holds once ``payload`` arrived.

    Raises :class:`~fedmap.errors.RejectedUpdate` when a broadcast is relative to a model this
    rover does not hold (decoding it would silently give a wrong model).
    """
    if kind == "none":
        return held
    if kind == "keyframe":
        return decode(payload)
    if kind not in ("broadcast", "chain"):
        raise RejectedUpdate(f"unknown downlink kind {kind!r}")
    have = model_version(held)
    if have != reference:
        raise RejectedUpdate(f"stale model: this rover holds version {have}, the {kind} is relative to {reference}")
    for p in unpack_chain(payload) if kind == "chain" else [payload]:
        held = decode(p, reference=held)
    return held


def total_local_steps(local_maps: list[GridMap], config: FederationConfig) -> int:
    return sum(config.rounds * config.local.epochs * steps_per_epoch(m.classes.size, config.local) for m in local_maps)


def rover_step(
    model,
    local: GridMap,
    held: Weights,
    encoder: Encoder,
    config: FederationConfig,
    *,
    round_idx: int,
    agent: int,
    on_step: Callable[[int, float], None] | None = None,
    select: np.ndarray | None = None,
) -> tuple[bytes, float | None]:
    """One rover's part of a round: start from ``held``, fit, check, encode.

    This is the one implementation of the rover side: the in-process runner and the
    Flower ClientApp both call it. ``round_idx`` is 0-based; the training seed is
    :func:`agent_seed` ``(config.seed, round_idx, agent)``. Returns the uplink payload
    (relative to ``held`` for update codecs) and the last training loss. Raises
    :class:`~fedmap.errors.RejectedUpdate` when training diverges or the weights are not
    finite; any other error is a mistake that stops the run. ``select`` restricts training to
    some cells (:func:`~fedmap.nets.training.fit`).
    """
    set_weights(model, held)
    seed = agent_seed(config.seed, round_idx, agent)
    steps = (fit(model, local, config.local, seed=seed, on_step=on_step) if select is None else
             fit(model, local, config.local, seed=seed, on_step=on_step, select=select))
    w = get_weights(model)
    if not all(np.isfinite(v).all() for v in w.values()):
        raise RejectedUpdate("update holds NaN or infinite weights")
    return encoder.encode(w, reference=held), (steps[-1] if steps else None)


@dataclass
class BaseStep:
    """What the base station made of one round's uplink payloads."""

    held: Weights  # the decoded broadcast: what base and rovers continue from
    downlink: bytes  # the broadcast payload
    counts: dict[int, float]  # aggregation weight of every agent whose update was used
    dropped: dict[int, str]  # agent -> why its payload was not used


def base_step(
    aggregator,
    held: Weights,
    payloads: dict[int, bytes],
    counts: dict[int, float],
    down_encoder: Encoder,
    *,
    dropped: dict[int, str] | None = None,
    round_label: int | None = None,
    versions: Mapping[int, str] | None = None,
    window: Mapping[str, Weights] | None = None,
) -> BaseStep:
    """The base station's part of a round: decode, aggregate, encode and decode the broadcast.

    The one implementation of the base side (in-process runner and Flower ServerApp).
    ``payloads`` and ``counts`` are keyed by agent id, aggregated in ascending agent
    order; a payload that does not decode is dropped with its reason. ``dropped`` holds
    agents already lost earlier in the round (they are kept in the result). ``versions``
    (agent -> :func:`model_version` of the model it trained from, as the rover reports it):
    an update made from any model but ``held`` is dropped, never decoded against ``held``,
    unless that model is in ``window`` (version -> weights, :attr:`Broadcaster.window`):
    then it is decoded against its own model and applied as a delta, ``held + (update -
    its model)``. Raises :class:`FedmapError` when no update is left.
    """
    dropped = dict(dropped or {})
    updates, used = [], {}
    current = model_version(held) if versions is not None else ""
    window = window or {}
    for k in sorted(payloads):
        made_from = held
        if versions is not None and versions.get(k) != current:
            if versions.get(k) not in window:
                dropped[k] = (f"stale reference: its update is relative to model version "
                              f"{versions.get(k) or 'unknown'}, the base holds {current}")
                continue
            made_from = window[versions[k]]
        try:
            update = decode(payloads[k], reference=made_from)
            _check_fits(update, held)
        except RejectedUpdate as e:
            dropped[k] = str(e)
            continue
        if made_from is not held:  # rebased: the rover's change, applied to the current model
            update = {n: (held[n] + (update[n] - made_from[n])).astype(held[n].dtype) for n in held}
        updates.append(update)
        used[k] = counts[k]
    if not updates:
        where = f"round {round_label}: " if round_label is not None else ""
        raise FedmapError(f"{where}every agent's update was dropped ({'; '.join(dropped.values()) or 'no agent replied'})")
    global_w = aggregator.aggregate(held, updates, list(used.values()))
    down_payload = down_encoder.encode(global_w, reference=held)
    return BaseStep(decode(down_payload, reference=held), down_payload, used, dict(sorted(dropped.items())))


def _check_fits(update: Weights, held: Weights) -> None:
    """A decoded update must have the tensors of the model the base holds, all finite."""
    if set(update) != set(held):
        raise RejectedUpdate(f"malformed payload: its tensors {sorted(set(update) ^ set(held))} do not match the model's")
    for name, value in held.items():
        if np.shape(update[name]) != np.shape(value):
            raise RejectedUpdate(f"malformed payload: tensor {name!r} has shape {np.shape(update[name])}, "
                                 f"the model's is {np.shape(value)}")
    # a rover checks its own update (rover_step), but a faulty or tampered one may not have:
    # one NaN would poison the global model of every rover
    for name, value in update.items():
        if not np.isfinite(value).all():
            raise RejectedUpdate(f"update holds NaN or infinite weights (tensor {name!r})")


def run_federation(
    init_weights: Weights,
    net_config: NetConfig,
    local_maps: list[GridMap],
    config: FederationConfig,
    *,
    on_step: Callable[[int, float], None] | None = None,
    on_round: Callable[[RoundRecord, Weights], None] | None = None,
    one_shot_cache: dict | None = None,
    absent: Mapping[int, Collection[int]] | None = None,
    restarted: Mapping[int, Collection[int]] | None = None,
) -> FederationResult:
    """Run ``config.rounds`` rounds of federated fitting of ``local_maps``.

    ``on_round(record, weights)`` is called after each round with its history record and
    the global weights the rovers now hold (e.g. to score the map after every round).

    ``one_shot_cache``: one-round runs that differ only in the server's aggregator train
    the rovers identically, so a dict passed here keeps the rovers' uplink payloads and
    later one-round runs with the same initial weights, maps, local training, seed and
    uplink codec reuse them instead of training again (e.g. FedAvg vs FedAdam vs FedYogi
    in the paper's Table II). Runs of more than one round ignore it.

    ``absent`` simulates rovers that miss rounds (round number, 1-based -> agents): they
    neither receive that round's downlink nor train, and keep their state. ``restarted``
    (round -> agents) makes rovers lose their state (model, uplink residual) before that
    round. Each rover holds its own model; the downlink each gets is
    :meth:`Broadcaster.for_rover`, so a rover that missed a broadcast gets a keyframe.
    """
    absent, restarted = absent or {}, restarted or {}
    check_same_frame(local_maps)
    aggregator = config.make_aggregator()
    up_spec, down_spec = CodecSpec.parse(config.uplink), CodecSpec.parse(config.downlink)
    held = init_held(init_weights)  # the initial model is known to all
    down_enc = Encoder(down_spec)
    bc = Broadcaster(held, window=config.versions_kept)
    rover_held = [held for _ in local_maps]  # what each rover holds
    up_encs = [Encoder(up_spec) for _ in local_maps]  # residuals live on the rovers
    model = build_model(net_config)
    history: list[RoundRecord] = []
    cache_key = None
    if one_shot_cache is not None and config.rounds == 1:
        cache_key = (config.uplink, config.local, config.seed, tuple(m.classes.tobytes() for m in local_maps),
                     tuple((k, v.tobytes()) for k, v in sorted(held.items())), tuple(sorted(absent.get(1, ()))))
    for r in range(config.rounds):
        t0 = time.perf_counter()
        for k in restarted.get(r + 1, ()):
            rover_held[k], up_encs[k] = init_held(init_weights), Encoder(up_spec)
        present = [k for k in range(len(local_maps)) if k not in set(absent.get(r + 1, ()))]
        if history:  # the last round's broadcast (or a keyframe) reaches the rovers present now
            _deliver(bc, rover_held, present, history[-1])
        payloads, losses, dropped = {}, {}, {}
        if cache_key is not None and one_shot_cache is not None and cache_key in one_shot_cache:
            payloads, losses, dropped = (dict(x) for x in one_shot_cache[cache_key])
        else:
            for k in present:
                try:
                    payloads[k], losses[k] = rover_step(model, local_maps[k], rover_held[k], up_encs[k], config,
                                                        round_idx=r, agent=k, on_step=on_step)
                except RejectedUpdate as e:
                    dropped[k] = str(e)
                if r == config.rounds - 1:  # its residual would only feed a next round: nothing reads it
                    up_encs[k].reset()  # (float64, 0.67 GB a rover at 4096², alive through the base's step)
                # a rover's fit and encoding leave freed blocks inside the heap, which the next
                # rover's allocations do not fit in exactly: without this the run's RSS grew by
                # each rover's (2048²: 2.0 GB after the first rover, 3.0 GB after the fourth)
                release_freed_memory()
            if cache_key is not None and one_shot_cache is not None:
                one_shot_cache[cache_key] = (dict(payloads), dict(losses), dict(dropped))
        counts: dict[int, float] = {k: local_maps[k].n_known for k in payloads}
        versions = {k: model_version(rover_held[k]) for k in payloads}
        step = base_step(aggregator, held, payloads, counts, down_enc, dropped=dropped, round_label=r + 1,
                         versions=versions, window=bc.window)
        held = step.held  # the base continues from the decoded broadcast, as the rovers will
        bc.advance(held, step.downlink)
        rec = round_record(r + 1, step, losses, {k: len(p) for k, p in payloads.items()}, up_spec, down_spec,
                           time.perf_counter() - t0, missing=sorted(set(range(len(local_maps))) - set(present)))
        history.append(rec)
        if on_round is not None:
            on_round(rec, held)
    if history:  # the final broadcast goes to the rovers that replied in the last round
        last = history[-1]
        _deliver(bc, rover_held, sorted(set(last.aggregation_counts) | set(last.dropped)), last)
    return FederationResult(held, history, {"name": config.aggregator, **aggregator.hyperparameters()})


def init_held(init_weights: Weights) -> Weights:
    """The initial model as every rover rebuilds it (float32)."""
    return {k: np.asarray(v, dtype=np.float32) for k, v in init_weights.items()}


def _deliver(bc: Broadcaster, rover_held: list[Weights], rovers: list[int], rec: RoundRecord) -> None:
    """In process: send ``rovers`` what :meth:`Broadcaster.for_rover` says, book it in ``rec``."""
    for k in rovers:
        d = bc.for_rover(model_version(rover_held[k]))
        rover_held[k] = apply_downlink(rover_held[k], d.kind, d.payload, d.reference)
        book_downlink(rec, k, d)


def book_downlink(rec: RoundRecord, agent: int, d: Downlink) -> None:
    """Count the downlink ``d`` sent to ``agent`` in the round record whose model it carries."""
    if d.kind == "none":
        return
    rec.downlink_bytes[agent] = len(d.payload)
    if d.kind == "keyframe" and agent not in rec.keyframes:
        rec.keyframes.append(agent)
        rec.keyframes.sort()


def round_record(round_no: int, step: BaseStep, losses: Mapping[int, float | None], up_bytes: dict[int, int],
                 up_spec: CodecSpec, down_spec: CodecSpec, seconds: float, *, missing: list[int] | None = None,
                 flower: FlowerRound | None = None) -> RoundRecord:
    """One round's entry of ``FederationResult.history`` (the same for every runner), made
    once the round is aggregated: nobody has its model yet (``downlink_bytes`` and
    ``keyframes`` are empty until :func:`book_downlink`)."""
    return RoundRecord(round=round_no, final_loss={k: losses.get(k) for k in step.counts},
                       aggregation_counts=dict(step.counts), dropped=step.dropped, missing=list(missing or []),
                       uplink_codec=up_spec.label(), downlink_codec=down_spec.label(), uplink_bytes=up_bytes,
                       downlink_bytes={}, keyframes=[], seconds=seconds, flower=flower)
