"""The ways of sharing maps, each with the same four hooks the mission loop calls.

Every sharing payload starts with a small header (real bytes, counted): the version of
the model an update is relative to, the sender's position and target (uplink, 16 bytes),
or what the body is, the model version a broadcast is relative to and every rover's last
reported position and target (downlink, 10 + 9 per rover bytes); rovers coordinate their
targets with it.

* ``none``: nothing is sent. A rover's belief is its own observations.
* ``raw``: a rover sends the cells it observed since its last *delivered* sync, as a
  class map (other cells UNKNOWN) coded with fedmap's lossless ``context`` codec
  (:mod:`fedmap.federation.mapcodec`). **Over budget**, it sends the newest cells that
  fit (every cell first observed at or after a cut-off step, the earliest cut-off that
  fits) and keeps the rest for the next sync; lost cells are sent again. The base
  overlays every delivered map on its global map (observations are truth, so they never
  conflict) and sends each rover the global map coded *against the last global map that
  rover acknowledged* (unchanged cells cost almost nothing); over budget it sends the
  cells it merged most recently that fit. With an elevation layer (``[mission] layers``)
  both directions also carry the heights of the same cells, quantised to
  ``elevation_q_m`` (:class:`~fedmap.federation.heights.HeightCodec` ``lossless``), after
  the class map; ``central`` shares every rover's heights too, the other strategies none.
* ``paper`` / ``fedmap``: the preset's network (:func:`fedmap.config.method_config`),
  trained and aggregated by the same :func:`~fedmap.federation.runner.rover_step` and
  :func:`~fedmap.federation.runner.base_step` as ``fedmap run``. A rover trains from the
  model it holds on its whole local map, 50 local epochs per sync
  (:data:`MISSION_DEFAULTS`). **Over budget** the update is not sent; the
  rover trains again at the next sync on its grown map. The versions protocol is the
  runner's (:class:`Model`): update codecs are relative to the model both ends hold, so
  the base aggregates only updates made from its current model (others are dropped as
  stale) and sends a rover that holds anything but the previous model a *keyframe*: the
  whole model, exact (:data:`fedmap.federation.runner.KEYFRAME`: fp32, zstd-compressed).
* ``central``: an oracle; every rover and the base see every observation at once, free.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any, TypeVar

import numpy as np
import torch

from fedmap.config import method_config
from fedmap.errors import FedmapError, RejectedUpdate
from fedmap.federation import streamcodec
from fedmap.federation.codecs import CodecSpec, Encoder
from fedmap.federation.heights import HeightCodec
from fedmap.federation.mapcodec import decode_map, encode_map
from fedmap.federation.runner import (
    Broadcaster,
    Downlink,
    apply_downlink,
    base_step,
    init_held,
    model_version,
    rover_step,
)
from fedmap.federation.streamcodec import initial_state
from fedmap.maps.grid import UNKNOWN, GridMap, classes_from_rgb
from fedmap.mission.sensing import disk_offsets
from fedmap.mission.settings import PREDICTIVE_OPTIONS
from fedmap.nets.model import Weights, build_model, get_weights, render, set_weights
from fedmap.pipeline import initial_weights

_UP = struct.Struct("<8shhhh")  # model version (8 bytes), row, col, target row, target col
_DOWN = struct.Struct("<B8sB")  # kind, reference model version (8 bytes), rovers reported
_REPORT = struct.Struct("<Bhhhh")  # rover, row, col, target row, target col
_KINDS = ("map", "broadcast", "keyframe", "chain", "chunk")
_CHUNK = struct.Struct("<B8sHHI")  # what is chunked (kind), the version it gives, chunk index, count, whole bytes
_LEN = struct.Struct("<I")  # the class map's length, before the heights (elevation layer)
#: Bytes of the uplink header (before the payload proper).
UP_HEADER = _UP.size
Cell = tuple[int, int]
T = TypeVar("T")
#: Settings a mission lays over a model strategy's preset (``[strategies.<name>]`` wins).
#: The presets' 100 local epochs fit a map from scratch in one round; at a sync a rover
#: starts from the global model and has observed ``sync_every`` more steps, so both model
#: strategies train 50 epochs per sync (the same compute for both).
MISSION_DEFAULTS: dict[str, dict] = {"paper": {"epochs": 50, "versions_kept": 8},
                                     "fedmap": {"epochs": 50, "versions_kept": 8}}
#: Rate control: the top-k fractions a model strategy tries, largest first, when an update in
#: its own codec does not fit the uplink budget (values int8, zstd, with error feedback).
RATE_FRACTIONS: tuple[float, ...] = (0.1, 0.03, 0.01, 0.003, 0.001, 0.0003)
#: ``train_on = "changed"``: the fewest replayed cells a sync trains on (when little changed).
MIN_REPLAY = 256
#: Torch threads while a mission trains or renders. The models are small and trained one
#: after another; on a shared 2-core machine two OpenMP threads per process spin against
#: other processes and made one GridNet fit 20x slower than one thread (measured: 17-23 s
#: vs 0.8 s for 20 epochs at 128² under load).
TORCH_THREADS = 1


@contextmanager
def torch_threads(n: int = TORCH_THREADS) -> Iterator[None]:
    """Run the block with ``n`` torch threads, then restore the previous setting."""
    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def _v(version: str) -> bytes:
    return bytes.fromhex(version) if version else bytes(8)


def _unv(raw: bytes) -> str:
    return "" if raw == bytes(8) else raw.hex()


def pack_up(version: str, pos: Cell, target: Cell | None, body: bytes) -> bytes:
    """Uplink: the version of the model the update is relative to ("" for none), position, target."""
    t = target if target is not None else (-1, -1)
    return _UP.pack(_v(version), pos[0], pos[1], t[0], t[1]) + body


def unpack_up(payload: bytes) -> tuple[str, Cell, Cell | None, bytes]:
    v, r, c, tr, tc = _UP.unpack_from(payload)
    return _unv(v), (r, c), (None if tr < 0 else (tr, tc)), payload[_UP.size:]


def pack_down(kind: str, reference: str, reports: dict[int, tuple[Cell, Cell | None]], body: bytes) -> bytes:
    """Downlink: what the body is (map, broadcast, keyframe), the model version a broadcast is
    relative to, and every rover's last reported position and target."""
    head = _DOWN.pack(_KINDS.index(kind), _v(reference), len(reports))
    for k, (p, t) in sorted(reports.items()):
        t = t if t is not None else (-1, -1)
        head += _REPORT.pack(k, p[0], p[1], t[0], t[1])
    return head + body


def unpack_down(payload: bytes) -> tuple[str, str, dict[int, tuple[Cell, Cell | None]], bytes]:
    kind, ref, n = _DOWN.unpack_from(payload)
    reports, off = {}, _DOWN.size
    for _ in range(n):
        k, r, c, tr, tc = _REPORT.unpack_from(payload, off)
        reports[k] = ((r, c), None if tr < 0 else (tr, tc))
        off += _REPORT.size
    return _KINDS[kind], _unv(ref), reports, payload[off:]


@dataclass(frozen=True)
class DroppedUpdate:
    """A model update that did not make it into the base's model: rejected by its rover's
    step (not sent), or delivered but not aggregated (e.g. stale). Its round, its rover
    (-1: the round's every update, when the base could use none) and why."""

    round: int
    rover: int
    why: str

    def to_dict(self) -> dict:
        return {"round": self.round, "rover": self.rover, "why": self.why}


@dataclass
class Outgoing:
    """A payload a strategy wants to send (``payload=None``: nothing fits the budget)."""

    payload: bytes | None
    kind: str
    ctx: dict = field(default_factory=dict)


class Strategy:
    """Base: no sharing. ``team`` is the mission's rover list (positions, local maps)."""

    name = "none"
    shares = False
    #: The model updates that did not make it into the base's model, in order. None for a
    #: strategy that sends no model updates, so has none to drop (``metrics.json`` then has
    #: no ``dropped_updates``).
    dropped: list[DroppedUpdate] | None = None
    #: Model strategies: at every sync, how many models behind the base each rover is (None
    #: for a strategy without models).
    lags: list[dict] | None = None

    def __init__(self, truth: GridMap, team: list, budget: dict[str, int | None]) -> None:
        self.truth = truth
        self.team = team
        self.budget = budget
        self.shape = truth.shape
        starts = {k: (r.pos, None) for k, r in enumerate(team)}
        self.known_reports: list[dict[int, tuple[Cell, Cell | None]]] = [dict(starts) for _ in team]
        self.base_reports: dict[int, tuple[Cell, Cell | None]] = dict(starts)

    # -- what rovers and base hold
    def held(self, k: int) -> np.ndarray:
        """The latest global map rover ``k`` holds (classes)."""
        return np.full(self.shape, UNKNOWN, dtype=np.uint8)

    def heights(self, k: int) -> np.ndarray | None:
        """The heights rover ``k`` holds from others (metres, NaN elsewhere), or None when
        this strategy shares no elevation."""
        return None

    def heights_version(self, k: int) -> int:
        """A counter that changes whenever :meth:`heights` of rover ``k`` does."""
        return 0

    def global_heights(self) -> np.ndarray | None:
        """The heights the base station holds (NaN elsewhere), or None without them."""
        return None

    def belief(self, k: int) -> np.ndarray:
        """Rover ``k``'s own observations laid over the global map it holds."""
        local = self.team[k].local
        return np.where(local != UNKNOWN, local, self.held(k)).astype(np.uint8)

    def global_map(self) -> np.ndarray:
        """The base station's global map (classes)."""
        return np.full(self.shape, UNKNOWN, dtype=np.uint8)

    def others(self, k: int) -> list[Cell]:
        """Other rovers' positions and targets as rover ``k`` last heard of them."""
        out = []
        for j, (p, t) in self.known_reports[k].items():
            if j != k:
                out.append(p)
                if t is not None:
                    out.append(t)
        return out

    # -- the link's hooks
    def uplink(self, k: int, round_no: int) -> Outgoing | None:
        return None

    def receive_uplink(self, k: int, payload: bytes, ctx: dict, round_no: int) -> None:
        pass

    def uplink_acked(self, k: int, ctx: dict) -> None:
        pass

    def base_round(self, round_no: int) -> dict[int, Outgoing]:
        return {}

    def receive_downlink(self, k: int, payload: bytes, ctx: dict) -> bool:
        """Apply a delivered downlink; False when it could not be used (stale)."""
        return False

    def at_sync(self, round_no: int) -> None:
        """Called at every sync, before the rovers' uplinks of round ``round_no``."""

    def _report(self, k: int) -> tuple[Cell, Cell | None]:
        r = self.team[k]
        return r.pos, r.target


class Central(Strategy):
    """The oracle: everything everyone observed, instantly, for free."""

    name = "central"

    def held(self, k: int) -> np.ndarray:
        return self.global_map()

    def global_map(self) -> np.ndarray:
        out = np.full(self.shape, UNKNOWN, dtype=np.uint8)
        for r in self.team:
            out = np.where(r.local != UNKNOWN, r.local, out)
        return out

    def heights(self, k: int) -> np.ndarray | None:
        zs = [r.heights for r in self.team if r.heights is not None]
        if not zs:
            return None
        out = np.full(self.shape, np.nan, dtype=np.float32)
        for z in zs:
            out = np.where(np.isfinite(z), z, out)
        return out

    def heights_version(self, k: int) -> int:
        return sum(int(np.isfinite(r.heights).sum()) for r in self.team if r.heights is not None)

    def global_heights(self) -> np.ndarray | None:
        return self.heights(0)

    def others(self, k: int) -> list[Cell]:
        out = []
        for j, r in enumerate(self.team):
            if j != k:
                out.append(r.pos)
                if r.target is not None:
                    out.append(r.target)
        return out


def _cut_to_budget(make, stamps: np.ndarray, candidates: np.ndarray, budget: int | None) -> tuple[bytes | None,
                                                                                                   np.ndarray]:
    """The payload of the most candidate cells that fits: every candidate cell stamped at or
    after a cut-off, the earliest cut-off that fits (:func:`_largest_fitting`). ``make(mask)``
    builds the payload of a cell mask. Returns ``(payload or None, mask sent)``."""
    cuts = np.unique(stamps[candidates])  # ascending: an earlier cut sends more

    def at(m: int) -> tuple[bytes, np.ndarray]:  # m + 1 cut-offs, the newest first
        mask = candidates if m == len(cuts) - 1 else candidates & (stamps >= cuts[len(cuts) - 1 - m])
        return make(mask), mask

    _, made = _largest_fitting(at, len(cuts) - 1, budget)
    return (None, np.zeros_like(candidates)) if made is None else made


class Raw(Strategy):
    """Lossless map merging with the ``context`` codec (see the module docstring)."""

    name = "raw"
    shares = True

    def __init__(self, truth: GridMap, team: list, budget: dict[str, int | None], *,
                 height_q: float | None = None) -> None:
        super().__init__(truth, team, budget)
        empty = np.full(self.shape, UNKNOWN, dtype=np.uint8)
        #: with an elevation layer: the step heights are quantised to (None: classes only)
        self.height_codec = None if height_q is None else HeightCodec("lossless", height_q)
        nan = np.full(self.shape, np.nan, dtype=np.float32)
        self._held_z = [nan.copy() for _ in team]
        self._z_version = [0 for _ in team]
        self.base_z = nan.copy()
        self.delivered = [np.zeros(self.shape, dtype=bool) for _ in team]  # cells the base has from each rover
        self._held = [empty.copy() for _ in team]
        self.base = empty.copy()
        self.base_stamp = np.full(self.shape, -1, dtype=np.int64)  # round each base cell was merged
        self.acked = [empty.copy() for _ in team]  # what the base knows each rover holds
        self.received: list[tuple[int, int, bytes]] = []  # (round, rover, payload) merged, in order

    def held(self, k: int) -> np.ndarray:
        return self._held[k]

    def heights(self, k: int) -> np.ndarray | None:
        return None if self.height_codec is None else self._held_z[k]

    def heights_version(self, k: int) -> int:
        return self._z_version[k]

    def global_heights(self) -> np.ndarray | None:
        return None if self.height_codec is None else self.base_z

    def global_map(self) -> np.ndarray:
        return self.base

    def _body(self, classes: bytes, z: np.ndarray | None, mask: np.ndarray) -> bytes:
        """The class map, and with an elevation layer the heights of the same cells after it."""
        if self.height_codec is None or z is None:
            return classes
        return _LEN.pack(len(classes)) + classes + self.height_codec.encode(np.where(mask, z, np.nan))

    def _split(self, body: bytes) -> tuple[bytes, np.ndarray | None]:
        if self.height_codec is None:
            return body, None
        (n,) = _LEN.unpack_from(body)
        return body[_LEN.size:_LEN.size + n], HeightCodec.decode(body[_LEN.size + n:])

    def uplink(self, k: int, round_no: int) -> Outgoing | None:
        r = self.team[k]
        pending = (r.local != UNKNOWN) & ~self.delivered[k]

        def make(mask: np.ndarray) -> bytes:
            classes = encode_map(np.where(mask, r.local, UNKNOWN).astype(np.uint8))
            return pack_up("", r.pos, r.target, self._body(classes, r.heights, mask & (r.local != UNKNOWN)))

        budget = self.budget["up"]
        payload, sent = _cut_to_budget(make, r.obs_step, pending, budget)
        return Outgoing(payload, "cells", {"sent": sent})

    def uplink_acked(self, k: int, ctx: dict) -> None:
        self.delivered[k] |= ctx["sent"]

    def receive_uplink(self, k: int, payload: bytes, ctx: dict, round_no: int) -> None:
        _, pos, target, body = unpack_up(payload)
        classes, z = self._split(body)
        cells = decode_map(classes, expected_shape=self.shape)
        if z is not None:
            self.base_z = np.where(np.isfinite(z), z, self.base_z).astype(np.float32)
        self.received.append((round_no, k, payload))
        new = (cells != UNKNOWN) & (self.base == UNKNOWN)
        self.base = np.where(cells != UNKNOWN, cells, self.base).astype(np.uint8)
        self.base_stamp[new] = round_no
        self.base_reports[k] = (pos, target)

    def base_round(self, round_no: int) -> dict[int, Outgoing]:
        out = {}
        for k in range(len(self.team)):
            ref = self.acked[k]  # always sent: even without new cells it carries the team's positions

            def make(mask: np.ndarray, ref: np.ndarray = ref) -> bytes:
                m = np.where(mask | (ref != UNKNOWN), self.base, UNKNOWN).astype(np.uint8)
                body = self._body(encode_map(m, reference=ref), self.base_z, mask & np.isfinite(self.base_z))
                return pack_down("map", "", self.base_reports, body)

            candidates = (self.base != UNKNOWN) & (ref == UNKNOWN)
            payload, sent = _cut_to_budget(make, self.base_stamp, candidates, self.budget["down"])
            full = np.where(sent | (ref != UNKNOWN), self.base, UNKNOWN).astype(np.uint8)
            out[k] = Outgoing(payload, "map", {"map": full})
        return out

    def receive_downlink(self, k: int, payload: bytes, ctx: dict) -> bool:
        _, _, reports, body = unpack_down(payload)
        classes, z = self._split(body)
        try:
            m = decode_map(classes, reference=self._held[k], expected_shape=self.shape)
        except RejectedUpdate:  # coded against a map this rover no longer holds
            return False
        if z is not None and np.isfinite(z).any():
            self._held_z[k] = np.where(np.isfinite(z), z, self._held_z[k]).astype(np.float32)
            self._z_version[k] += 1
        self._held[k] = m
        self.acked[k] = ctx["map"]
        self.known_reports[k].update(reports)
        return True


class Model(Strategy):
    """A network shared with fedmap's rover and base steps (``paper`` or ``fedmap``).

    The protocol is the runner's: :func:`~fedmap.federation.runner.rover_step` and
    :func:`~fedmap.federation.runner.base_step` (which drops an update made from any model
    but the base's), :class:`~fedmap.federation.runner.Broadcaster` (the round's broadcast
    for a rover that holds the previous model, a keyframe for any other) and
    :func:`~fedmap.federation.runner.apply_downlink` on the rover. Versions are
    :func:`~fedmap.federation.runner.model_version` content hashes (8 bytes on the link).
    """

    shares = True

    def __init__(self, truth: GridMap, team: list, budget: dict[str, int | None], *, method: str,
                 settings: dict, seed: int, train_on: str = "map", replay: float = 1.0) -> None:
        super().__init__(truth, team, budget)
        self.name = method
        self.train_on, self.replay, self.seed = train_on, replay, seed
        self.last_trained = [-1 for _ in team]  # the step each rover last trained at (-1: never)
        self.trained_cells: list[dict] = []  # per training: round, rover, cells trained on
        pc = method_config(method, **{**MISSION_DEFAULTS.get(method, {}), **settings, "seed": seed})
        self.fed = pc.federation
        self.net_config = pc.model.network(self.shape[0])
        init = init_held(initial_weights(pc, self.shape[0]))
        self.model = build_model(self.net_config)
        self.aggregator = self.fed.make_aggregator()
        self.up_update = CodecSpec.parse(self.fed.uplink).update
        self.up_encs = [Encoder(self.fed.uplink) for _ in team]  # residuals live on the rovers
        self.rate_state: list[Weights | None] = [None for _ in team]  # the rate-controlled top-k's residual
        self.down_rate_state: Weights | None = None  # the base's rate-controlled broadcasts' residual
        self.down_enc = Encoder(self.fed.downlink)
        self.bc = Broadcaster(init, window=self.fed.versions_kept)  # the base's models, broadcasts and keyframe
        self.versions: dict[str, np.ndarray] = {}  # model version -> rendered classes (cache)
        self.rover_held: list[Weights] = [init for _ in team]
        self.rover_version = [self.bc.version for _ in team]
        self.acked_version: list[str | None] = [self.bc.version for _ in team]  # what the base knows each rover holds
        self.inbox: dict[int, tuple[str, bytes, float]] = {}
        self.order = [self.bc.version]  # every model the base has held, in order
        self.lags: list[dict] = []  # at every sync: how many models behind each rover is
        self.sending: dict[int, dict] = {}  # base: rover -> the downlink it is sending in chunks
        self.receiving: dict[int, dict] = {}  # rover -> the chunks of a downlink it has so far
        self.rounds_aggregated = 0
        self.dropped: list[DroppedUpdate] = []
        self.losses: list[dict] = []

    @property
    def base_held(self) -> Weights:
        assert self.bc.held is not None
        return self.bc.held

    def _render(self, version: str, w: Weights) -> np.ndarray:
        if version not in self.versions:
            set_weights(self.model, w)
            with torch_threads():
                self.versions[version] = classes_from_rgb(render(self.model, *self.shape))
        return self.versions[version]

    def held(self, k: int) -> np.ndarray:
        return self._render(self.rover_version[k], self.rover_held[k])

    def global_map(self) -> np.ndarray:
        return self._render(self.bc.version, self.base_held)

    def uplink(self, k: int, round_no: int) -> Outgoing | None:
        r = self.team[k]
        local = self.truth.with_classes(r.local, f"rover {k}")
        before = self.up_encs[k].state()
        select = self._selection(k, round_no)
        try:
            with torch_threads():
                body, loss = rover_step(self.model, local, self.rover_held[k], self.up_encs[k], self.fed,
                                        round_idx=round_no - 1, agent=k, select=select)
        except RejectedUpdate as e:
            self.dropped.append(DroppedUpdate(round_no, k, str(e)))
            return None
        self.losses.append({"round": round_no, "rover": k, "loss": loss})
        kind = "update" if self.up_update else "model"
        payload: bytes | None = pack_up(self.rover_version[k], r.pos, r.target, body)
        b = self.budget["up"]
        if b is not None and payload is not None and len(payload) > b:  # rate control: the best update that fits
            self.up_encs[k].restore(before)  # the update that did not fit was not sent
            payload, kind = self._fitted_update(k, r, b)
        return Outgoing(payload, kind, {"known": local.n_known})

    def _selection(self, k: int, round_no: int) -> np.ndarray | None:
        """``train_on = "changed"``: the cells rover ``k`` observed since it last trained, and
        a seeded replay sample of ``replay`` times as many of the rest it trains on (known
        cells for a masked preset, every cell for the paper's); None: its whole map."""
        r = self.team[k]
        since = self.last_trained[k]
        self.last_trained[k] = int(r.obs_step.max())
        if self.train_on == "map" or since < 0:
            self.trained_cells.append({"round": round_no, "rover": k, "cells": int((r.local != UNKNOWN).sum())
                                       if self.fed.local.masked else int(r.local.size)})
            return None
        changed = r.obs_step > since
        pool = np.flatnonzero(((r.local != UNKNOWN) if self.fed.local.masked else np.ones(r.local.shape, bool))
                              & ~changed)
        n = min(len(pool), max(int(math.ceil(self.replay * int(changed.sum()))), MIN_REPLAY))
        rng = np.random.default_rng(np.random.SeedSequence([self.seed, round_no, k, 9]))
        select = changed.copy()
        select.reshape(-1)[rng.choice(pool, size=n, replace=False)] = True
        self.trained_cells.append({"round": round_no, "rover": k, "cells": int(select.sum())})
        return select

    def _fitted_update(self, k: int, r, budget: int) -> tuple[bytes | None, str]:
        """Top-k of the update just trained (the model's weights now), rate-controlled
        (:func:`_rate_controlled`) to ``budget`` (None: none fits). The rover's top-k encoder
        keeps its own residual, carried from one sync to the next."""
        w = get_weights(self.model)
        payload, label, state = _rate_controlled(
            self.rate_state[k],
            lambda enc: pack_up(self.rover_version[k], r.pos, r.target, enc.encode(w, reference=self.rover_held[k])),
            lambda p: len(p) <= budget)
        if state is None:
            return None, "update"
        self.rate_state[k] = state
        return payload, f"update {label}"

    def receive_uplink(self, k: int, payload: bytes, ctx: dict, round_no: int) -> None:
        version, pos, target, body = unpack_up(payload)
        self.base_reports[k] = (pos, target)
        self.acked_version[k] = version
        self.inbox[k] = (version, body, float(ctx["known"]))

    def base_round(self, round_no: int) -> dict[int, Outgoing]:
        payloads = {k: body for k, (_, body, _) in self.inbox.items()}
        counts = {k: known for k, (_, _, known) in self.inbox.items()}
        versions = {k: v for k, (v, _, _) in self.inbox.items()}
        self.inbox = {}
        if payloads:
            try:
                with torch_threads():
                    step = self._aggregate(round_no, payloads, counts, versions)
            except FedmapError as e:  # every update was dropped (e.g. stale): no new model this round
                self.dropped.append(DroppedUpdate(round_no, -1, str(e)))
            else:
                for k, why in step.dropped.items():
                    self.dropped.append(DroppedUpdate(round_no, k, why))
                self.bc.advance(step.held, step.downlink)
                self.order.append(self.bc.version)
                self.rounds_aggregated += 1
        out = {}
        b = self.budget["down"]
        for k in range(len(self.team)):
            d = self.bc.for_rover(self.acked_version[k])
            if d.kind == "none":
                self.sending.pop(k, None)
                continue  # it holds the current model
            payload = pack_down(d.kind, d.reference, self.base_reports, d.payload)
            if b is None or len(payload) <= b:
                self.sending.pop(k, None)
                out[k] = Outgoing(payload, d.kind, {})
            else:
                out[k] = self._chunk(k, d, b)
        return out

    def _aggregate(self, round_no: int, payloads: dict, counts: dict, versions: dict):
        """:func:`base_step`, with rate control: when the broadcast in the downlink codec does
        not fit the downlink budget, the largest top-k fraction of :data:`RATE_FRACTIONS` that
        fits (values int8, zstd, the base's own error feedback). The base continues from the
        decoded broadcast either way, so every rover that decodes it holds the same model."""
        before = self.down_enc.state()
        step = base_step(self.aggregator, self.base_held, payloads, counts, self.down_enc, round_label=round_no,
                         versions=versions, window=self.bc.window)
        b = self.budget["down"]
        room = None if b is None else b - len(pack_down("broadcast", self.bc.version, self.base_reports, b""))
        if room is None or len(step.downlink) <= room:
            return step
        self.down_enc.restore(before)  # the broadcast that did not fit was not sent
        step, _, state = _rate_controlled(
            self.down_rate_state,
            lambda enc: base_step(self.aggregator, self.base_held, payloads, counts, enc, round_label=round_no,
                                  versions=versions, window=self.bc.window),
            lambda st: len(st.downlink) <= room)
        if state is not None:
            self.down_rate_state = state
        return step  # when none fits: the smallest, in chunks

    def _chunk(self, k: int, d: Downlink, budget: int) -> Outgoing:
        """The next chunk of a downlink ``d`` too big for one round's budget. A transfer keeps
        what it started with while the model it gives is in the base's window (the rover then
        catches up from there with a broadcast or chain) and the rover still holds what it
        decodes against; else it restarts with ``d``."""
        t = self.sending.get(k)
        usable = t is not None and (t["version"] == self.bc.version or t["version"] in self.bc.window) and \
            (t["kind"] == "keyframe" or t["reference"] == self.acked_version[k])
        if t is None or not usable:
            size = budget - len(pack_down("chunk", d.reference, self.base_reports, b"")) - _CHUNK.size
            n = -(-len(d.payload) // size) if size > 0 else 0
            if size <= 0 or n > 0xFFFF:
                return Outgoing(None, d.kind, {})
            t = {"kind": d.kind, "reference": d.reference, "version": self.bc.version, "data": d.payload,
                 "size": size, "n": n, "have": set()}
            self.sending[k] = t
        i = min(set(range(t["n"])) - t["have"])  # the first chunk not delivered yet (a lost one again)
        part = t["data"][i * t["size"]:(i + 1) * t["size"]]
        body = _CHUNK.pack(_KINDS.index(t["kind"]), _v(t["version"]), i, t["n"], len(t["data"])) + part
        return Outgoing(pack_down("chunk", t["reference"], self.base_reports, body), f"{t['kind']} chunk", {})

    def lag(self, k: int) -> int | None:
        """How many models behind the base's current one rover ``k`` is (None: it holds none
        the base has held in this run)."""
        v = self.rover_version[k]
        return len(self.order) - 1 - self.order.index(v) if v in self.order else None

    def at_sync(self, round_no: int) -> None:
        self.lags.append({"round": round_no, "lag": [self.lag(k) for k in range(len(self.team))]})

    def receive_downlink(self, k: int, payload: bytes, ctx: dict) -> bool:
        kind, reference, reports, body = unpack_down(payload)
        if kind == "chunk":
            return self._receive_chunk(k, reference, reports, body)
        try:
            w = apply_downlink(self.rover_held[k], kind, body, reference)
        except RejectedUpdate:  # relative to a model this rover does not hold
            return False
        self.rover_held[k], self.rover_version[k] = w, model_version(w)
        self.acked_version[k] = self.rover_version[k]  # the link-level acknowledgement
        self.known_reports[k].update(reports)
        return True

    def _receive_chunk(self, k: int, reference: str, reports: dict, body: bytes) -> bool:
        kind_i, raw_version, i, n, total = _CHUNK.unpack_from(body)
        kind, version = _KINDS[kind_i], _unv(raw_version)
        key = (kind, reference, version, n, total)
        r = self.receiving.get(k)
        if r is None or r["key"] != key:
            r = self.receiving[k] = {"key": key, "parts": {}}
        r["parts"][i] = body[_CHUNK.size:]
        self.known_reports[k].update(reports)
        t = self.sending.get(k)
        if t is not None and (t["kind"], t["reference"], t["version"], t["n"], len(t["data"])) == key:
            t["have"].add(i)  # the link-level acknowledgement of this chunk
        if len(r["parts"]) < n:
            return True
        del self.receiving[k]
        blob = b"".join(r["parts"][j] for j in range(n))
        try:
            w = apply_downlink(self.rover_held[k], kind, blob, reference)
        except RejectedUpdate:
            return False
        if len(blob) != total or model_version(w) != version:
            return False
        self.rover_held[k], self.rover_version[k] = w, version
        self.acked_version[k] = version
        self.sending.pop(k, None)
        return True


def _rate_controlled(state: Weights | None, attempt: Callable[[Encoder], T],
                     fits: Callable[[T], bool]) -> tuple[T, str, Weights | None]:
    """Rate control: ``attempt`` with a top-k encoder (int8 values, zstd, its error feedback
    restored from ``state``) at each of :data:`RATE_FRACTIONS`, largest first. Returns the
    first result that ``fits``, its codec label and the encoder's new state; or, when none
    fits, the last (smallest) result, its label and None (the state is left as it was)."""
    for fraction in RATE_FRACTIONS:
        enc = Encoder(f"topk:{fraction},values=int8+zstd")
        enc.restore(state)
        out = attempt(enc)
        if fits(out):
            return out, f"top-k {fraction:g}", enc.state()
    return out, f"top-k {fraction:g}", None


def make_strategy(name: str, truth: GridMap, team: list, budget: dict[str, int | None], *, methods: dict,
                  seed: int, radius: float, height_q: float | None = None, train_on: str = "map",
                  replay: float = 1.0) -> Strategy:
    """A fresh strategy of ``name`` for one run (``height_q``: share heights at that step,
    with an elevation layer; ``raw`` and ``central`` do)."""
    if name == "none":
        return Strategy(truth, team, budget)
    if name == "central":
        return Central(truth, team, budget)
    if name == "raw":
        return Raw(truth, team, budget, height_q=height_q)
    if name == "predictive":
        return Predictive(truth, team, budget, radius=radius, options=methods.get(name))
    return Model(truth, team, budget, method=name, settings=dict(methods.get(name, {})), seed=seed,
                 train_on=train_on, replay=replay)


def cover(positions, shape: tuple[int, int], radius: float) -> np.ndarray:
    """Boolean ``shape`` map of every cell within ``radius`` of any of ``positions`` (the
    footprints of a trail without line of sight: the cells a trail may have observed)."""
    out = np.zeros(shape, dtype=bool)
    p = np.asarray(list(positions), dtype=np.int64).reshape(-1, 2)
    if p.size:
        off = disk_offsets(radius)
        rr = (p[:, None, 0] + off[None, :, 0]).ravel()
        cc = (p[:, None, 1] + off[None, :, 1]).ravel()
        ok = (rr >= 0) & (rr < shape[0]) & (cc >= 0) & (cc < shape[1])
        out[rr[ok], cc[ok]] = True
    return out


class Predictive(Strategy):
    """Lossless sharing of new cells with a persistent, learned probability model
    (:mod:`fedmap.federation.streamcodec`); see the module docstring for the protocol.

    Per rover, each direction of its link has a coder state on both ends. An uplink
    carries the rover's trail since the last one the base acknowledged (its moves), its
    target, and its observed cells within sensor range of that trail that the base does
    not hold: neither from this rover nor in the global map the rover holds. A downlink
    carries the other rovers' trails the rover does not hold, their targets, and every
    cell of the global map the rover does not hold (cells within sensor range of those
    trails cost least). The receiver derives which cells are candidates from the trails.
    **Over budget**, an uplink carries the longest prefix of its trail that fits (and the
    cells in range of it), a downlink the same share of every other rover's trail.
    """

    name = "predictive"
    shares = True

    def __init__(self, truth: GridMap, team: list, budget: dict[str, int | None], *, radius: float,
                 options: dict | None = None) -> None:
        super().__init__(truth, team, budget)
        n, shape = len(team), self.shape
        self.radius = radius
        opts = {k: v[0] for k, v in PREDICTIVE_OPTIONS.items()} | dict(options or {})
        self.derive_mask = opts["mask"] == "derived"
        self.persist = opts["state"] == "persistent"
        self.initial = init = initial_state() if opts["prior"] == "learned" else streamcodec.blank_state()
        empty = np.full(shape, UNKNOWN, dtype=np.uint8)
        starts = [r.pos for r in team]
        # rover side
        self.up_rover = [init.copy() for _ in team]
        self.down_rover = [init.copy() for _ in team]
        self.r_sent = [1] * n  # entries of its own trail the base holds (the start is known)
        self.r_delivered = [np.zeros(shape, dtype=bool) for _ in team]  # own cells the base holds
        self.r_held = [empty.copy() for _ in team]
        self.r_target = [None] * n  # its own target as the base holds it
        self.r_trails = [[[s] for s in starts] for _ in team]  # rover k's copy of every trail
        self.r_targets: list[list[Cell | None]] = [[None] * n for _ in team]
        # base side
        self.up_base = [init.copy() for _ in team]
        self.down_base = [init.copy() for _ in team]
        self.b_trails = [[s] for s in starts]
        self.b_from = [np.zeros(shape, dtype=bool) for _ in team]
        self.b_held = [empty.copy() for _ in team]
        self.b_targets: list[Cell | None] = [None] * n
        self.b_fwd = [[1] * n for _ in team]  # entries of rover j's trail that rover k holds
        self.b_fwd_targets: list[list[Cell | None]] = [[None] * n for _ in team]
        self.base = empty.copy()

    def held(self, k: int) -> np.ndarray:
        return self.r_held[k]

    def global_map(self) -> np.ndarray:
        return self.base

    def _candidates(self, anchors: list[Cell]):
        def derive(tracks: list[list[Cell]]) -> np.ndarray:
            if not self.derive_mask:
                return np.ones(self.shape, dtype=bool)
            return cover([*anchors, *(p for t in tracks for p in t)], self.shape, self.radius)
        return derive

    def _fold(self, state: streamcodec.CoderState, fold: streamcodec.Fold) -> None:
        if self.persist:
            state.fold(fold)

    def _rover_known(self, k: int) -> np.ndarray:
        r = self.team[k]
        return np.where(self.r_held[k] != UNKNOWN, self.r_held[k],
                        np.where(self.r_delivered[k], r.local, UNKNOWN)).astype(np.uint8)

    def _base_known(self, k: int) -> np.ndarray:
        return np.where(self.b_held[k] != UNKNOWN, self.b_held[k],
                        np.where(self.b_from[k], self.base, UNKNOWN)).astype(np.uint8)

    # -- uplink
    def uplink(self, k: int, round_no: int) -> Outgoing | None:
        r = self.team[k]
        known = self._rover_known(k)
        a = self.r_sent[k]
        anchor = r.trail[a - 1]
        pending = r.trail[a:]
        derive = self._candidates([anchor])

        def make(n: int) -> tuple[bytes, streamcodec.Fold, np.ndarray]:
            cand = derive([pending[:n]]) & (known == UNKNOWN)
            cells = np.where(cand, r.local, UNKNOWN).astype(np.uint8)
            content = streamcodec.Content([list(pending[:n])], [r.target], cells)
            payload, fold = streamcodec.encode(content, state=self.up_rover[k], anchors=[anchor],
                                               mark_refs=[self.r_target[k]], known=known, candidates=derive)
            return payload, fold, cells

        n, made = _largest_fitting(make, len(pending), self.budget["up"])
        if n is None:
            return Outgoing(None, "cells", {})
        payload, fold, cells = made
        return Outgoing(payload, "cells", {"n": n, "fold": fold, "cells": cells, "target": r.target})

    def receive_uplink(self, k: int, payload: bytes, ctx: dict, round_no: int) -> None:
        a = self.b_trails[k][-1]
        try:
            got = streamcodec.decode(payload, state=self.up_base[k], anchors=[a], mark_refs=[self.b_targets[k]],
                                     known=self._base_known(k), candidates=self._candidates([a]))
        except RejectedUpdate:
            ctx["used"] = False
            return
        ctx["used"] = True
        self._fold(self.up_base[k], got.fold)
        self.b_trails[k].extend(got.tracks[0])
        self.b_targets[k] = got.marks[0]
        carried = got.cells != UNKNOWN
        self.b_from[k] |= carried
        self.base = np.where(carried, got.cells, self.base).astype(np.uint8)

    def uplink_acked(self, k: int, ctx: dict) -> None:
        if not ctx.get("used"):
            return
        self._fold(self.up_rover[k], ctx["fold"])
        self.r_sent[k] += ctx["n"]
        self.r_delivered[k] |= ctx["cells"] != UNKNOWN
        self.r_target[k] = ctx["target"]

    # -- downlink
    def base_round(self, round_no: int) -> dict[int, Outgoing]:
        out = {}
        n_team = len(self.team)
        for k in range(n_team):
            others = [j for j in range(n_team) if j != k]
            known = self._base_known(k)
            anchors = [self.b_trails[j][self.b_fwd[k][j] - 1] for j in others]
            news = [self.b_trails[j][self.b_fwd[k][j]:] for j in others]
            marks = [self.b_targets[j] for j in others]
            refs = [self.b_fwd_targets[k][j] for j in others]
            lacking = (self.base != UNKNOWN) & (known == UNKNOWN)
            if not lacking.any() and not any(news) and marks == refs:
                continue  # it holds everything the base has
            derive = self._candidates(anchors)
            longest = max((len(t) for t in news), default=0)

            def make(n: int, news=news, derive=derive, known=known, lacking=lacking, anchors=anchors, marks=marks,
                     refs=refs, k=k, longest=longest) -> tuple[bytes, streamcodec.Fold, list[list[Cell]], np.ndarray]:
                share = [t[:-(-len(t) * n // longest)] if longest else [] for t in news]
                if n == longest:
                    cells = np.where(lacking, self.base, UNKNOWN).astype(np.uint8)
                else:
                    cells = np.where(lacking & derive(share), self.base, UNKNOWN).astype(np.uint8)
                content = streamcodec.Content(share, marks, cells)
                payload, fold = streamcodec.encode(content, state=self.down_base[k], anchors=anchors, mark_refs=refs,
                                                   known=known, candidates=derive)
                return payload, fold, share, cells

            n, made = _largest_fitting(make, longest, self.budget["down"])
            if n is None:
                out[k] = Outgoing(None, "map", {})
                continue
            payload, fold, share, cells = made
            out[k] = Outgoing(payload, "map", {"fold": fold, "tracks": share, "cells": cells, "marks": marks,
                                               "others": others})
        return out

    def receive_downlink(self, k: int, payload: bytes, ctx: dict) -> bool:
        others = ctx["others"]
        anchors = [self.r_trails[k][j][-1] for j in others]
        try:
            got = streamcodec.decode(payload, state=self.down_rover[k], anchors=anchors,
                                     mark_refs=[self.r_targets[k][j] for j in others], known=self._rover_known(k),
                                     candidates=self._candidates(anchors))
        except RejectedUpdate:  # coded against a state or map this rover no longer holds
            return False
        # the rover's end
        self._fold(self.down_rover[k], got.fold)
        carried = got.cells != UNKNOWN
        self.r_held[k] = np.where(carried, got.cells, self.r_held[k]).astype(np.uint8)
        for j, track, mark in zip(others, got.tracks, got.marks):
            self.r_trails[k][j].extend(track)
            self.r_targets[k][j] = mark
            self.known_reports[k][j] = (self.r_trails[k][j][-1], mark)
        # the base's end: the link-level acknowledgement
        self._fold(self.down_base[k], ctx["fold"])
        self.b_held[k] = np.where(ctx["cells"] != UNKNOWN, ctx["cells"], self.b_held[k]).astype(np.uint8)
        for j, track, mark in zip(others, ctx["tracks"], ctx["marks"]):
            self.b_fwd[k][j] += len(track)
            self.b_fwd_targets[k][j] = mark
        return True


def _largest_fitting(make, longest: int, budget: int | None) -> tuple[int | None, Any]:
    """The largest ``n`` in ``0..longest`` whose ``made = make(n)`` fits ``budget`` (``made``
    is a payload or a tuple that starts with one; sizes grow with ``n``), by binary search
    after trying ``longest``: ``(n, made)``, or ``(None, None)`` when even ``n = 0`` does not fit."""
    def size(made) -> int:
        return len(made[0] if isinstance(made, tuple) else made)

    full = make(longest)
    if budget is None or size(full) <= budget:
        return longest, full
    lo, hi = 0, longest - 1
    best: tuple[int | None, Any] = (None, None)
    while lo <= hi:
        mid = (lo + hi) // 2
        made = make(mid)
        if size(made) <= budget:
            best, lo = (mid, made), mid + 1
        else:
            hi = mid - 1
    return best
