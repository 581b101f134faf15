"""``paper`` and ``fedmap``: a network shared with fedmap's rover and base steps, as a rover
end (:class:`ModelRover`) and a base end (:class:`ModelBase`).

The preset's network (:func:`fedmap.config.method_config`) is trained and aggregated by the
same :func:`~fedmap.federation.runner.rover_step` and
:func:`~fedmap.federation.runner.base_step` as ``fedmap run``. A rover trains from the model
it holds on its whole local map, 50 local epochs per sync (:data:`MISSION_DEFAULTS`).
**Over budget** the best top-k update that fits is sent (rate control), or none; the rover
trains again at the next sync on its grown map. The versions protocol is the runner's:
update codecs are relative to the model both ends hold, so the base aggregates only
updates made from a model in its window (others are dropped as stale) and sends a rover
that holds anything else a *keyframe*: the whole model, exact
(:data:`fedmap.federation.runner.KEYFRAME`: fp32, zstd-compressed). A downlink over the
budget goes in chunks over the rounds. An uplink carries, after its header, the number of
cells the rover's map knows (4 bytes: FedAvg's weight ``n_k``).
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np

from fedmap.config import PipelineConfig
from fedmap.errors import FedmapError, RejectedUpdate
from fedmap.federation.codecs import CodecSpec, Encoder
from fedmap.federation.runner import Broadcaster, Downlink, apply_downlink, base_step, model_version, rover_step
from fedmap.maps.grid import UNKNOWN, GridMap, classes_from_rgb
from fedmap.mission.ends.protocol import (
    KINDS,
    BaseEnd,
    Cell,
    DroppedUpdate,
    Journal,
    Outgoing,
    RoverEnd,
    pack_down,
    pack_up,
    torch_threads,
    unpack_down,
    unpack_up,
    unv8,
    v8,
)
from fedmap.nets.model import Weights, build_model, get_weights, render, set_weights

T = TypeVar("T")
_CHUNK = struct.Struct("<B8sHHI")  # what is chunked (kind), the version it gives, chunk index, count, whole bytes
_COUNT = struct.Struct("<I")  # the cells the rover's map knows (FedAvg's weight), after the uplink header
#: Bytes of the known-cell count a model uplink carries after its header.
COUNT_BYTES = _COUNT.size
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


def rate_controlled(state: Weights | None, attempt: Callable[[Encoder], T],
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


class _Renderer:
    """The classes a model renders, cached by its version."""

    def __init__(self, pc: PipelineConfig, shape: tuple[int, int]) -> None:
        self.shape = shape
        self.model = build_model(pc.model.network(shape[0]))
        self.cache: dict[str, np.ndarray] = {}

    def __call__(self, version: str, w: Weights) -> np.ndarray:
        if version not in self.cache:
            set_weights(self.model, w)
            with torch_threads():
                self.cache[version] = classes_from_rgb(render(self.model, *self.shape))
        return self.cache[version]


@dataclass(frozen=True)
class Training:
    """How a rover of a model strategy trains at a sync (``[mission] train_on``, ``replay``)."""

    train_on: str = "map"
    replay: float = 1.0
    seed: int = 0


class ModelRover(RoverEnd):
    """A rover's end of a model strategy: its network, the model it holds, its update
    encoders (their residuals), and a downlink it is putting together from chunks."""

    def __init__(self, k: int, rover: Any, starts: list[Cell], *, truth: GridMap, pc: PipelineConfig,
                 init: Weights, budget: int | None, training: Training, journal: Journal) -> None:
        super().__init__(k, rover, starts)
        self.truth, self.fed, self.budget, self.training, self.journal = truth, pc.federation, budget, training, journal
        self.render = _Renderer(pc, self.shape)
        self.model = self.render.model
        self.up_update = CodecSpec.parse(self.fed.uplink).update
        self.enc = Encoder(self.fed.uplink)  # its residual lives on the rover
        self.rate_state: Weights | None = None  # the rate-controlled top-k's residual
        self.held_w: Weights = init
        self.version = model_version(init)
        self.last_trained = -1  # the step it last trained at (-1: never)
        self.receiving: dict | None = None  # the chunks of a downlink it has so far
        #: what :meth:`prepare`'s call trained: (round, encoder state before, (body, loss) or the
        #: rejection, its known cells)
        self.trained: tuple[int, Weights | None, tuple | RejectedUpdate, int] | None = None

    def held(self) -> np.ndarray:
        return self.render(self.version, self.held_w)

    def prepare(self, round_no: int) -> Callable[[], None]:
        """Its training for this round's uplink, as a call that touches this rover alone (its
        network, encoder and map), so the rovers of a sync can train side by side
        (:meth:`~fedmap.mission.ends.protocol.RoverEnd.prepare`); :meth:`uplink` then sends it."""
        r, k = self.rover, self.k
        local = self.truth.with_classes(r.local, f"rover {k}")
        before = self.enc.state()
        select = self._selection(round_no)

        def train() -> None:
            try:
                with torch_threads():
                    out: tuple | RejectedUpdate = rover_step(self.model, local, self.held_w, self.enc, self.fed,
                                                             round_idx=round_no - 1, agent=k, select=select)
            except RejectedUpdate as e:
                out = e
            self.trained = (round_no, before, out, local.n_known)

        return train

    def uplink(self, round_no: int) -> Outgoing | None:
        r, k = self.rover, self.k
        if self.trained is None or self.trained[0] != round_no:
            self.prepare(round_no)()
        assert self.trained is not None
        _, before, out, known = self.trained
        self.trained = None
        if isinstance(out, RejectedUpdate):
            assert self.journal.dropped is not None
            self.journal.dropped.append(DroppedUpdate(round_no, k, str(out)))
            return None
        body, loss = out
        self.journal.losses.append({"round": round_no, "rover": k, "loss": loss})
        kind = "update" if self.up_update else "model"
        count = _COUNT.pack(known)
        payload: bytes | None = pack_up(self.version, r.pos, r.target, count + body)
        b = self.budget
        if b is not None and payload is not None and len(payload) > b:  # rate control: the best update that fits
            self.enc.restore(before)  # the update that did not fit was not sent
            payload, kind = self._fitted_update(count, b)
        return Outgoing(payload, kind)

    def _selection(self, round_no: int) -> np.ndarray | None:
        """``train_on = "changed"``: the cells it observed since it last trained, and a seeded
        replay sample of ``replay`` times as many of the rest it trains on (known cells for a
        masked preset, every cell for the paper's); None: its whole map."""
        r, tr = self.rover, self.training
        since = self.last_trained
        self.last_trained = int(r.obs_step.max())
        masked = self.fed.local.masked
        if tr.train_on == "map" or since < 0:
            self.journal.trained_cells.append({"round": round_no, "rover": self.k, "cells": int(
                (r.local != UNKNOWN).sum()) if masked else int(r.local.size)})
            return None
        changed = r.obs_step > since
        pool = np.flatnonzero(((r.local != UNKNOWN) if masked else np.ones(r.local.shape, bool)) & ~changed)
        n = min(len(pool), max(int(math.ceil(tr.replay * int(changed.sum()))), MIN_REPLAY))
        rng = np.random.default_rng(np.random.SeedSequence([tr.seed, round_no, self.k, 9]))
        select = changed.copy()
        select.reshape(-1)[rng.choice(pool, size=n, replace=False)] = True
        self.journal.trained_cells.append({"round": round_no, "rover": self.k, "cells": int(select.sum())})
        return select

    def _fitted_update(self, count: bytes, budget: int) -> tuple[bytes | None, str]:
        """Top-k of the update just trained (the model's weights now), rate-controlled
        (:func:`rate_controlled`) to ``budget`` (None: none fits). The top-k encoder keeps
        its own residual, carried from one sync to the next."""
        w, r = get_weights(self.model), self.rover
        payload, label, state = rate_controlled(
            self.rate_state,
            lambda enc: pack_up(self.version, r.pos, r.target, count + enc.encode(w, reference=self.held_w)),
            lambda p: len(p) <= budget)
        if state is None:
            return None, "update"
        self.rate_state = state
        return payload, f"update {label}"

    def receive(self, payload: bytes) -> bool:
        kind, reference, reports, body = unpack_down(payload)
        if kind == "chunk":
            return self._receive_chunk(reference, reports, body)
        try:
            w = apply_downlink(self.held_w, kind, body, reference)
        except RejectedUpdate:  # relative to a model this rover does not hold
            return False
        self.held_w, self.version = w, model_version(w)
        self.reports.update(reports)
        return True

    def _receive_chunk(self, reference: str, reports: dict, body: bytes) -> bool:
        kind_i, raw_version, i, n, total = _CHUNK.unpack_from(body)
        kind, version = KINDS[kind_i], unv8(raw_version)
        key = (kind, reference, version, n, total)
        r = self.receiving
        if r is None or r["key"] != key:
            r = self.receiving = {"key": key, "parts": {}}
        r["parts"][i] = body[_CHUNK.size:]
        self.reports.update(reports)
        if len(r["parts"]) < n:
            return True
        self.receiving = None
        blob = b"".join(r["parts"][j] for j in range(n))
        try:
            w = apply_downlink(self.held_w, kind, blob, reference)
        except RejectedUpdate:
            return False
        if len(blob) != total or model_version(w) != version:
            return False
        self.held_w, self.version = w, version
        return True


class ModelBase(BaseEnd):
    """The base station's end of a model strategy: the aggregator, its models and broadcasts
    (:class:`~fedmap.federation.runner.Broadcaster`), the model it knows each rover holds,
    and the downlinks it is sending in chunks."""

    def __init__(self, shape: tuple[int, int], starts: list[Cell], *, pc: PipelineConfig, init: Weights,
                 budget: int | None, journal: Journal) -> None:
        super().__init__(shape, starts)
        self.fed, self.budget, self.journal = pc.federation, budget, journal
        self.render = _Renderer(pc, shape)
        self.aggregator = self.fed.make_aggregator()
        self.down_rate_state: Weights | None = None  # the rate-controlled broadcasts' residual
        self.down_enc = Encoder(self.fed.downlink)
        self.bc = Broadcaster(init, window=self.fed.versions_kept)
        self.acked_version: list[str | None] = [self.bc.version] * self.n  # what it knows each rover holds
        self.inbox: dict[int, tuple[str, bytes, float]] = {}
        self.order = [self.bc.version]  # every model it has held, in order
        self.sending: dict[int, dict] = {}  # rover -> the downlink it is sending in chunks
        self._pending: dict[tuple[int, int], tuple] = {}  # (rover, round) -> what a downlink in flight gives
        self.rounds_aggregated = 0

    @property
    def held_w(self) -> Weights:
        assert self.bc.held is not None
        return self.bc.held

    def global_map(self) -> np.ndarray:
        return self.render(self.bc.version, self.held_w)

    def lag(self, version: str) -> int | None:
        """How many models behind its current one a rover holding ``version`` is (None: a
        model it never held)."""
        return len(self.order) - 1 - self.order.index(version) if version in self.order else None

    def receive(self, k: int, payload: bytes, round_no: int) -> bool:
        version, pos, target, body = unpack_up(payload)
        (known,) = _COUNT.unpack_from(body)
        self.reports[k] = (pos, target)
        self.acked_version[k] = version
        self.inbox[k] = (version, body[_COUNT.size:], float(known))
        return True

    def downlinks(self, round_no: int) -> dict[int, Outgoing]:
        payloads = {k: body for k, (_, body, _) in self.inbox.items()}
        counts = {k: known for k, (_, _, known) in self.inbox.items()}
        versions = {k: v for k, (v, _, _) in self.inbox.items()}
        self.inbox = {}
        dropped = self.journal.dropped
        assert dropped is not None
        if payloads:
            try:
                with torch_threads():
                    step = self._aggregate(round_no, payloads, counts, versions)
            except FedmapError as e:  # every update was dropped (e.g. stale): no new model this round
                dropped.append(DroppedUpdate(round_no, -1, str(e)))
            else:
                for k, why in step.dropped.items():
                    dropped.append(DroppedUpdate(round_no, k, why))
                self.bc.advance(step.held, step.downlink)
                self.order.append(self.bc.version)
                self.rounds_aggregated += 1
        out = {}
        b = self.budget
        for k in range(self.n):
            d = self.bc.for_rover(self.acked_version[k])
            if d.kind == "none":
                self.sending.pop(k, None)
                continue  # it holds the current model
            payload = pack_down(d.kind, d.reference, self.reports, d.payload)
            if b is None or len(payload) <= b:
                self.sending.pop(k, None)
                self._pending[k, round_no] = ("whole", self.bc.version)
                out[k] = Outgoing(payload, d.kind)
            else:
                out[k] = self._chunk(k, round_no, d, b)
        return out

    def delivered(self, k: int, round_no: int, ok: bool) -> None:
        sent = self._pending.pop((k, round_no), None)
        if sent is None:
            return
        if sent[0] == "whole":
            if ok:
                self.acked_version[k] = sent[1]
            return
        _, key, i = sent
        t = self.sending.get(k)
        if not ok or t is None or self._key(t) != key:
            return
        t["have"].add(i)  # the chunk arrived
        if len(t["have"]) == t["n"]:  # and with it the whole downlink
            self.acked_version[k] = t["version"]
            self.sending.pop(k, None)

    @staticmethod
    def _key(t: dict) -> tuple:
        return (t["kind"], t["reference"], t["version"], t["n"], len(t["data"]))

    def _aggregate(self, round_no: int, payloads: dict, counts: dict, versions: dict):
        """:func:`base_step`, with rate control: when the broadcast in the downlink codec does
        not fit the downlink budget, the largest top-k fraction of :data:`RATE_FRACTIONS` that
        fits (values int8, zstd, the base's own error feedback). The base continues from the
        decoded broadcast either way, so every rover that decodes it holds the same model."""
        before = self.down_enc.state()
        step = base_step(self.aggregator, self.held_w, payloads, counts, self.down_enc, round_label=round_no,
                         versions=versions, window=self.bc.window)
        b = self.budget
        room = None if b is None else b - len(pack_down("broadcast", self.bc.version, self.reports, b""))
        if room is None or len(step.downlink) <= room:
            return step
        self.down_enc.restore(before)  # the broadcast that did not fit was not sent
        step, _, state = rate_controlled(
            self.down_rate_state,
            lambda enc: base_step(self.aggregator, self.held_w, payloads, counts, enc, round_label=round_no,
                                  versions=versions, window=self.bc.window),
            lambda st: len(st.downlink) <= room)
        if state is not None:
            self.down_rate_state = state
        return step  # when none fits: the smallest, in chunks

    def _chunk(self, k: int, round_no: int, d: Downlink, budget: int) -> Outgoing:
        """The next chunk of a downlink ``d`` too big for one round's budget. A transfer keeps
        what it started with while the model it gives is in the base's window (the rover then
        catches up from there with a broadcast or chain) and the rover still holds what it
        decodes against; else it restarts with ``d``."""
        t = self.sending.get(k)
        usable = t is not None and (t["version"] == self.bc.version or t["version"] in self.bc.window) and \
            (t["kind"] == "keyframe" or t["reference"] == self.acked_version[k])
        if t is None or not usable:
            size = budget - len(pack_down("chunk", d.reference, self.reports, b"")) - _CHUNK.size
            n = -(-len(d.payload) // size) if size > 0 else 0
            if size <= 0 or n > 0xFFFF:
                return Outgoing(None, d.kind)
            t = {"kind": d.kind, "reference": d.reference, "version": self.bc.version, "data": d.payload,
                 "size": size, "n": n, "have": set()}
            self.sending[k] = t
        i = min(set(range(t["n"])) - t["have"])  # the first chunk not delivered yet (a lost one again)
        part = t["data"][i * t["size"]:(i + 1) * t["size"]]
        body = _CHUNK.pack(KINDS.index(t["kind"]), v8(t["version"]), i, t["n"], len(t["data"])) + part
        self._pending[k, round_no] = ("chunk", self._key(t), i)
        return Outgoing(pack_down("chunk", t["reference"], self.reports, body), f"{t['kind']} chunk")


def model_lags(base: ModelBase, rovers: list[ModelRover]) -> list[int | None]:
    """How many models behind the base each rover is (the record's ``model_lag``)."""
    return [base.lag(r.version) for r in rovers]
