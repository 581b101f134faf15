"""The base station: a Flower ``ServerApp`` running fedmap's strategy for R rounds.

:class:`FedmapStrategy` is a Flower ``Strategy`` whose aggregation is
:func:`fedmap.federation.runner.base_step` (fedmap's FedAvg / FedAdam / FedYogi /
coverage math), so a run equals :func:`~fedmap.federation.runner.run_federation` for the
same seed and settings. ``strategy.start`` drives the rounds; the run config's
``deadline`` is the per-round timeout, so a rover that never replies cannot hang the
base: the round aggregates the survivors and records who was missing and why.

While the run goes, ``<out>.run/`` holds ``status.json`` (state, round, message) and an
atomic checkpoint ``checkpoint_round{r}/`` after every round (:mod:`fedmap.flower.checkpoint`:
model, server optimiser moments, downlink residual, ledger; the last ``keep-checkpoints``
are kept); ``resume=<checkpoint>`` continues a crashed run from one. At the end the kept
rounds' models are copied into ``<out>/`` as ``global_model_round{r}.safetensors``.
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import replace
from logging import INFO, WARNING
from pathlib import Path
from typing import Any

import numpy as np
from flwr.app import ArrayRecord, ConfigRecord, Context, Message, MessageType, MetricRecord, RecordDict
from flwr.serverapp import Grid, ServerApp
from flwr.serverapp.strategy import Strategy
from flwr.supercore import log

from fedmap.errors import FedmapError
from fedmap.federation.codecs import CodecSpec, Encoder
from fedmap.federation.runner import (
    Broadcaster,
    Downlink,
    FederationResult,
    FlowerRound,
    RoundRecord,
    base_step,
    book_downlink,
    round_record,
)
from fedmap.flower.checkpoint import BaseState, read_checkpoint
from fedmap.flower.polling import REPLY_LOST, exchange, quick_pulls
from fedmap.flower.records import check_flower_count, from_record, to_record
from fedmap.flower.settings import RunSettings
from fedmap.flower.task import (
    KEY_ROVER,
    initial_weights,
    parse_rover_nodes,
    save_checkpoint,
    truth_shape,
    write_base_outputs,
    write_status,
    wrong_key,
)
from fedmap.nets.model import Weights

app = ServerApp()
quick_pulls()  # a reply's objects: Flower's first retry after 1 s
#: Seconds between the base station's polls for replies (Flower's ``send_and_receive``: 3 s).
POLL = 0.25


#: A reply whose message arrived but whose body (the objects) did not (Flower's
#: :data:`~fedmap.flower.polling.REPLY_LOST`: the link dropped mid-transfer), recorded as a
#: missing rover like one whose reply never came.
LOST_REPLY = "reply lost on the link"
#: Why a rover is missing: it was sent the round and no reply came in time, or none of the
#: nodes the round was sent to is that rover (it was not connected when the round began).
NO_REPLY = "no reply before the round's deadline"
NOT_CONNECTED = "not connected when the round began"


def _take_uplink(pid: int, msg: Message, shape: tuple[int, int], team: tuple[int, int] | None, payloads: dict,
                 counts: dict, losses: dict, dropped: dict, flower_up: dict) -> None:
    """Rover ``pid``'s reply ``msg`` (its map of ``shape``; the team's is ``team``) into the
    round: its uplink, cell count, loss and Flower's byte count, or why it was dropped."""
    met = _metrics(msg)
    if shape != team:
        assert team is not None
        dropped[pid] = f"rover {pid}: its map is {shape[0]}x{shape[1]}, the team's is {team[0]}x{team[1]}"
        return
    if "error" in msg.content.config_records:
        error = msg.content["error"]
        if error.get("fatal", False):  # a mistake, not a rejected update: the run stops
            raise FedmapError(f"rover {pid}: {str(error['reason'])}")
        dropped[pid] = str(error["reason"])
        return
    record = msg.content.array_records["uplink"]
    payloads[pid] = from_record(record)
    flower_up[pid] = check_flower_count(record, len(payloads[pid]))
    counts[pid] = float(met["known-cells"])
    losses[pid] = float(met["loss"]) if "loss" in met else None


class FedmapStrategy(Strategy):
    """fedmap's rounds on Flower: payloads in, ``base_step`` aggregation, broadcast out.

    What each rover is sent comes from :class:`~fedmap.federation.runner.Broadcaster`: the
    round's broadcast to a rover that holds the model it is relative to, a keyframe to
    any other (it missed a round, restarted, or its node is new). Every reply reports the
    version of the model the rover holds; an update made from another model than the base's
    is dropped, never decoded against the wrong reference.

    The team's map size is the ground truth's (``truth`` / ``terrain``) when the base has
    one, else the size most rovers report in the first round (a tie goes to the larger
    map); a rover with another size is dropped with its size in the reason.

    Parameters
    ----------
    settings : RunSettings
        Rounds, aggregator, codecs, rovers / min-rovers, deadline, ...
    sleep : callable
        Used while waiting for rovers to connect (tests pass a fake clock).
    """

    def __init__(self, settings: RunSettings, *, sleep=time.sleep, run_config: dict | None = None) -> None:
        self.settings = settings
        self.run_config = dict(run_config or {})  # kept in checkpoints: --resume rebuilds the run from it
        self.offset = 0  # rounds completed before this Flower run (a resumed run)
        fed = settings.federation
        self.aggregator = fed.make_aggregator()
        self.up_spec, self.down_spec = CodecSpec.parse(fed.uplink), CodecSpec.parse(fed.downlink)
        self.down_encoder = Encoder(self.down_spec)
        self.held: Weights | None = None  # what the base holds; the initial model until round 1 ends
        # the initial model is built once the team's size is known
        self.broadcaster = Broadcaster(None, window=fed.versions_kept)
        self.shape: tuple[int, int] | None = truth_shape(settings)
        self.history: list[RoundRecord] = []
        self.node_partition: dict[int, int] = {}  # Flower node id -> rover index
        self.key_rover = parse_rover_nodes(settings.base.rover_nodes)  # node id -> the rover its registered key is for
        self.node_version: dict[int, str] = {}  # Flower node id -> version of the model it holds
        self._sleep = sleep
        self._t0 = 0.0
        self._sent: dict[str, int] = {}  # message id -> node id of the last messages sent
        self._resent: Counter[int] = Counter()  # node id -> copies of its message sent again this round
        self._down: dict[int, tuple[Downlink, int]] = {}  # node id -> what it was sent, Flower's byte count
        if settings.base.resume:
            self.resume(read_checkpoint(Path(settings.base.resume)))

    # -- helpers ---------------------------------------------------------------------------

    def _wait_for_nodes(self, grid: Grid, want: int) -> list[int]:
        """Connected node ids once ``want`` are there or ``connect_timeout`` has passed."""
        s = self.settings
        t_end = time.monotonic() + s.base.connect_timeout
        while len(nodes := sorted(grid.get_node_ids())) < want and time.monotonic() < t_end:
            self._sleep(0.5)
        if len(nodes) < s.base.min_rovers:
            raise FedmapError(f"only {len(nodes)} rover(s) connected after {s.base.connect_timeout:g} s, "
                              f"fewer than min-rovers={s.base.min_rovers}; start more rovers or lower min-rovers")
        return nodes

    def _messages(self, nodes: list[int], kind: str, server_round: int) -> list[Message]:
        msgs, self._down = [], {}
        for n in nodes:
            d = self.broadcaster.for_rover(self.node_version.get(n))
            arrays = to_record(d.payload)
            self._down[n] = (d, check_flower_count(arrays, len(d.payload)))
            config = ConfigRecord({"server-round": server_round, "downlink-kind": d.kind,
                                   "reference-version": d.reference, KEY_ROVER: self.key_rover.get(n, -1)})
            msgs.append(Message(RecordDict({"downlink": arrays, "config": config}), dst_node_id=n, message_type=kind))
        # Flower's message id is the object id (set when pushed); error replies made by the
        # SuperLink (e.g. "node unavailable") come from the SuperLink's own node id, so the
        # rover they concern is found through the message they reply to
        self._sent = {m.object_id: n for m, n in zip(msgs, nodes)}
        self._resent = Counter()
        return msgs

    def resent(self, copies: list[Message]) -> None:
        """The round's exchange sent ``copies`` of unanswered messages again: their replies
        (or the SuperLink's errors for them) concern the same nodes."""
        for c in copies:
            self._sent[c.object_id] = c.metadata.dst_node_id
            self._resent[c.metadata.dst_node_id] += 1

    def _delivered(self, node: int, pid: int) -> None:
        """``node`` (rover ``pid``) replied: it got what it was sent; book it in the record of
        the model it carries (the previous round's), under the rover's partition id."""
        if not self.history or node not in self._down:
            return
        d, flower = self._down[node]
        rec = self.history[-1]
        book_downlink(rec, pid, d)
        if d.kind != "none":
            _flower(rec).downlink_bytes[pid] = flower

    def _team_shape(self, shapes: dict[int, tuple[int, int]]) -> tuple[int, int]:
        """The team's map size: the ground truth's, else the first round's majority (tie: larger)."""
        if self.shape is None:
            votes = Counter(shapes.values())
            self.shape = max(votes, key=lambda sh: (votes[sh], sh))
        return self.shape

    # -- Strategy --------------------------------------------------------------------------

    def configure_train(self, server_round: int, arrays: ArrayRecord, config: ConfigRecord, grid: Grid) -> list[Message]:
        s = self.settings
        first = server_round == 1  # of this Flower run: a resumed run waits for the whole team again
        server_round += self.offset  # the run's round number (training seeds depend on it)
        nodes = self._wait_for_nodes(grid, s.base.rovers if first else s.base.min_rovers)
        log(INFO, "fedmap: round %d: sending to %d rover(s)", server_round, len(nodes))
        write_status(s.out, "running", round=server_round, nodes=len(nodes))
        self._t0 = time.perf_counter()
        return self._messages(nodes, MessageType.TRAIN, server_round)

    def aggregate_train(self, server_round: int, replies) -> tuple[ArrayRecord | None, MetricRecord | None]:
        s = self.settings
        server_round += self.offset
        payloads: dict[int, bytes] = {}
        counts: dict[int, float] = {}
        losses: dict[int, float | None] = {}
        dropped: dict[int, str] = {}
        flower_up: dict[int, int] = {}
        node_errors: dict[str, str] = {}
        missing_why: dict[int, str] = {}
        versions: dict[int, str] = {}
        good: list[tuple[int, int, Message]] = []
        for msg in replies:
            node = self._sent.get(msg.metadata.reply_to_message_id, msg.metadata.src_node_id)
            if msg.has_error():  # the ClientApp crashed or the node went away: nothing delivered
                pid = self.node_partition.get(node)
                reason = f"Flower error {msg.error.code}: {msg.error.reason}".splitlines()[0]
                if REPLY_LOST in msg.error.reason:  # the link dropped while the reply's body was on its way
                    reason = f"{LOST_REPLY} ({reason})"
                if pid is None:
                    node_errors[str(node)] = reason
                else:
                    missing_why[pid] = reason
                continue
            met = msg.content["metrics"]
            if "partition-id" not in met:  # the rover could not even read its settings or map
                error: Any = msg.content["error"]
                raise FedmapError(f"a rover (node {node}) failed before training: {error['reason']}")
            pid = int(met["partition-id"])
            bound = self.key_rover.get(node)
            if bound is not None and bound != pid:  # a rover's key is its number: refused, whatever it sent
                node_errors[str(node)] = wrong_key(node, bound, pid)
                log(WARNING, "fedmap: %s", node_errors[str(node)])
                continue
            self.node_partition[node] = pid
            if "state" in msg.content.config_records:
                self.node_version[node] = str(msg.content["state"]["held-version"])
            self._delivered(node, pid)
            good.append((node, pid, msg))
        shapes = {pid: (int(_metrics(m)["height"]), int(_metrics(m)["width"])) for _, pid, m in good}
        team = self._team_shape(shapes) if shapes else self.shape
        for node, pid, msg in good:
            _take_uplink(pid, msg, shapes[pid], team, payloads, counts, losses, dropped, flower_up)
            if pid in payloads:
                versions[pid] = self.node_version.get(node, "")
        # a rover none of whose nodes was sent this round (every node sent is known, none is it)
        # was not connected when the round began: a restarted rover still starting, say
        sent = [self.node_partition.get(n) for n in self._sent.values()]
        for pid in set(range(s.base.rovers)) - set(payloads) - set(dropped) - set(missing_why):
            missing_why[pid] = NOT_CONNECTED if None not in sent and pid not in sent else NO_REPLY
        missing = sorted(missing_why)
        if len(payloads) < s.base.min_rovers:
            raise FedmapError(
                f"round {server_round}: {len(payloads)} rover(s) delivered an update, fewer than min-rovers="
                f"{s.base.min_rovers} (missing: {missing or 'none'}; dropped: {dropped or 'none'})")
        assert self.shape is not None  # set by the first replies; at least min-rovers >= 1 replied
        if self.held is None:
            self.held = initial_weights(s, self.shape[0])
            self.broadcaster.reset(self.held)
        step = base_step(self.aggregator, self.held, payloads, counts, self.down_encoder, dropped=dropped,
                         round_label=server_round, versions=versions, window=self.broadcaster.window)
        self.held = step.held
        self.broadcaster.advance(step.held, step.downlink)
        resent = {self.node_partition[n]: k for n, k in self._resent.items() if n in self.node_partition}
        flower = FlowerRound(missing_why=dict(sorted(missing_why.items())), node_errors=node_errors,
                             uplink_bytes=dict(sorted(flower_up.items())), downlink_bytes={},
                             resent=dict(sorted(resent.items())))
        rec = round_record(server_round, step, losses, {k: len(p) for k, p in sorted(payloads.items())},
                           self.up_spec, self.down_spec, time.perf_counter() - self._t0, missing=missing, flower=flower)
        self.history.append(rec)
        log(INFO, "fedmap: round %d aggregated %d rover(s); missing %s; dropped %s", server_round,
            len(step.counts), missing, list(step.dropped))
        return to_record(step.downlink), MetricRecord({"rovers-used": len(step.counts),
                                                       "uplink-bytes": sum(rec.uplink_bytes.values())})

    def configure_evaluate(self, server_round: int, arrays: ArrayRecord, config: ConfigRecord, grid: Grid) -> list[Message]:
        if server_round + self.offset < self.settings.federation.rounds:
            return []  # broadcasts ride on the next round's train messages
        # the final model goes to the rovers that replied in the last round (used or dropped):
        # a rover that died may still be listed as connected, and waiting for it would cost a deadline
        last = set(self.history[-1].aggregation_counts) | set(self.history[-1].dropped) if self.history else set()
        nodes = sorted(n for n in grid.get_node_ids() if self.node_partition.get(n) in last)
        return self._messages(nodes, MessageType.EVALUATE, server_round + self.offset)

    def aggregate_evaluate(self, server_round: int, replies) -> MetricRecord | None:
        acked = []
        for m in replies:
            if m.has_error() or "partition-id" not in m.content["metrics"]:
                continue
            node = self._sent.get(m.metadata.reply_to_message_id, m.metadata.src_node_id)
            pid = int(m.content["metrics"]["partition-id"])
            self._delivered(node, pid)
            acked.append(pid)
        acked.sort()
        if self.history:
            rec = self.history[-1]
            self.history[-1] = replace(rec, flower=replace(_flower(rec), final_broadcast_received_by=acked))
        return None

    def summary(self) -> None:
        s = self.settings
        log(INFO, "fedmap strategy: %s, %d round(s), uplink %s, downlink %s, %d rovers (min %d), deadline %g s",
            s.federation.aggregator, s.federation.rounds, self.up_spec.label(), self.down_spec.label(), s.base.rovers,
            s.base.min_rovers, s.base.deadline)

    # -- per round, on the base ---------------------------------------------------------------

    def checkpoint(self, server_round: int, arrays: ArrayRecord) -> MetricRecord | None:
        """``evaluate_fn`` hook: after every round, save all the base needs to resume, atomically."""
        if server_round == 0 or self.held is None:
            return None
        assert self.shape is not None  # set before the first aggregation, as held is
        moments = {w: dict(getattr(self.aggregator, w)) for w in ("m", "v") if getattr(self.aggregator, w, None)}
        save_checkpoint(self.settings, BaseState(server_round + self.offset, self.held, moments,
                                                 self.down_encoder.state(), self.history, self.shape,
                                                 self.run_config))
        return None

    def resume(self, state: BaseState) -> None:
        """Continue after ``state.round`` rounds: the global model, the server optimiser's
        moments, the downlink encoder's residual and the ledger as they were. Rovers are
        new to this run: each gets a keyframe of the global model first."""
        if self.shape is not None and self.shape != state.shape:
            raise FedmapError(f"the checkpoint's maps are {state.shape}, this run's ground truth is {self.shape}")
        self.offset, self.held, self.shape = state.round, state.held, state.shape
        self.history = state.history
        self.broadcaster.reset(state.held)
        for w, weights in state.moments.items():
            setattr(self.aggregator, w, {k: np.asarray(v, dtype=np.float64) for k, v in weights.items()})
        self.down_encoder.restore(state.down_encoder)

    def result(self) -> FederationResult:
        assert self.held is not None, "no round was aggregated"
        return FederationResult(self.held, self.history, {"name": self.settings.federation.aggregator,
                                                          **self.aggregator.hyperparameters()})


def _flower(rec: RoundRecord) -> FlowerRound:
    """The Flower part of a round record of this base station (every one has it)."""
    assert rec.flower is not None, f"round {rec.round} has no Flower record"
    return rec.flower


def _metrics(msg: Message) -> Any:
    """A reply's metrics (the ClientApp writes numbers only)."""
    return msg.content["metrics"]


class FirstRoundGrid(Grid):
    """``grid`` whose first exchange waits ``first`` seconds for replies, every later one the
    timeout it is given (the deadline): Flower's strategy takes one timeout for every round,
    and the first round's also covers each rover's start-up. Everything else is ``grid``'s."""

    def __init__(self, grid: Grid, first: float, on_resend: Callable[[list[Message]], None] | None = None) -> None:
        self._grid: Grid = grid
        self._first: float | None = first
        self._on_resend = on_resend

    @property
    def run(self) -> Any:
        return self._grid.run

    def set_run(self, run: Any) -> None:
        self._grid.set_run(run)

    def create_message(self, content: Any, message_type: str, dst_node_id: int, group_id: str,
                       ttl: float | None = None) -> Message:
        return self._grid.create_message(content, message_type, dst_node_id, group_id, ttl)

    def get_node_ids(self) -> Iterable[int]:
        return self._grid.get_node_ids()

    def get_nodes(self) -> Iterable[Any]:
        return self._grid.get_nodes()

    def push_messages(self, messages: Iterable[Message]) -> Iterable[str]:
        return self._grid.push_messages(messages)

    def pull_messages(self, message_ids: Iterable[str]) -> Iterable[Message]:
        return self._grid.pull_messages(message_ids)

    def send_and_receive(self, messages: Iterable[Message], *, timeout: float | None = None) -> Iterable[Message]:
        """The round's exchange, which keeps its deadline even for a reply cut on the link
        (:func:`~fedmap.flower.polling.exchange`; Flower's own waited for such a reply's body
        until the SuperLink dropped its upload session, 180 s, and took no reply that arrived
        whole meanwhile). A message that goes unanswered far longer than the others took is
        sent again (an instruction lost on the link would otherwise cost the whole deadline);
        the rover answers a copy of a message it answered with the same reply."""
        wait, self._first = (timeout if self._first is None else self._first), None
        return exchange(self._grid, list(messages), float("inf") if wait is None else wait, poll=POLL, resend=True,
                        on_resend=self._on_resend)


def run_base_station(grid: Grid, settings: RunSettings, run_config: dict | None = None) -> Path:
    """R rounds on ``grid`` (those left after the ``resume`` checkpoint), then render,
    refine, evaluate and write the outputs."""
    t0 = time.perf_counter()
    strategy = FedmapStrategy(settings, run_config=run_config)
    left = settings.federation.rounds - strategy.offset
    if left < 1:
        raise FedmapError(f"nothing to resume: the checkpoint is after round {strategy.offset} of "
                          f"{settings.federation.rounds}")
    first = settings.base.first_deadline or settings.base.deadline
    strategy.start(grid=FirstRoundGrid(grid, first, on_resend=strategy.resent), initial_arrays=to_record(b""),
                   num_rounds=left, timeout=settings.base.deadline, evaluate_fn=strategy.checkpoint)
    fed = strategy.result()
    flower = {
        "settings": settings.record(),
        "missing": {r.round: r.missing for r in fed.history},
        "flower_bytes": [{"round": r.round, "uplink": _flower(r).uplink_bytes, "downlink": _flower(r).downlink_bytes}
                         for r in fed.history],
    }
    assert strategy.shape is not None  # set with the first aggregated round
    return write_base_outputs(fed, strategy.shape, settings, flower, federation_s=time.perf_counter() - t0)


@app.main()
def main(grid: Grid, context: Context) -> None:
    settings = RunSettings.from_run_config(dict(context.run_config))
    try:
        out = run_base_station(grid, settings, dict(context.run_config))
    except Exception as e:  # the base-station command waits on this file: never leave it "running"
        msg = str(e) if isinstance(e, FedmapError) else f"{type(e).__name__}: {e}".splitlines()[0]
        write_status(settings.out, "failed", message=msg)
        log(INFO, "fedmap: error: %s", msg)
        raise
    log(INFO, "fedmap: outputs in %s", out)
