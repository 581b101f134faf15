"""The rover: a Flower ``ClientApp`` that trains on its own local map.

Each ``train`` message carries the base station's downlink payload (empty in round 1:
every rover rebuilds the initial model, as in the in-process runner). The rover decodes
it relative to the model it holds, trains (:func:`fedmap.flower.task.train_round`) and
replies with its uplink payload and its number of known cells. What the rover holds
between rounds (the decoded global model and its uplink encoder with the error-feedback
residual) lives in ``context.state``.

A rejected update (:class:`~fedmap.errors.RejectedUpdate`) is reported in the reply and
the base drops this rover for the round; any other error is reported as ``fatal`` and
stops the run.

The final ``evaluate`` message delivers the last global model; with ``out=<dir>`` in the
node config the rover saves it there with its rendering, and with ``done-file=<path>`` it
writes that file (``fedmap rover`` then stops its SuperNode: the run is over).

The base sends a message again when its reply is long overdue (the message, or the reply,
may have been lost on the link). A copy of the message the rover last answered (same type
and round) is answered with the same reply, from ``context.state``: the rover neither
trains twice nor decodes a broadcast twice.
"""

from __future__ import annotations

import functools
import pickle
from pathlib import Path
from typing import cast

import numpy as np
from flwr.app import (
    Array,
    ArrayRecord,
    ConfigRecord,
    ConfigRecordValues,
    Context,
    Message,
    MetricRecord,
    MetricRecordValues,
    RecordDict,
)
from flwr.clientapp import ClientApp
from flwr.supercore.cli.flower_superexec import flower_superexec
from flwr.supernode.cli.flwr_clientapp import flwr_clientapp

from fedmap._util import atomic_write_bytes
from fedmap.errors import FedmapError, RejectedUpdate
from fedmap.federation.codecs import Encoder
from fedmap.federation.runner import model_version
from fedmap.flower.faults import inject
from fedmap.flower.records import from_record, to_record
from fedmap.flower.settings import RunSettings
from fedmap.flower.task import KEY_ROVER, check_key, load_local_map, receive, rover_state, save_received, train_round
from fedmap.nets.model import Weights

app = ClientApp()

_HELD, _ENCODER = "fedmap.held", "fedmap.encoder"
#: What the rover last answered (message type and round), and the records of its reply.
_ANSWERED, _ANSWER = "fedmap.answered", "fedmap.answer."


def _key(msg: Message) -> str:
    config = msg.content.config_records.get("config")
    return f"{msg.metadata.message_type}@{config.get('server-round', '')!s}" if config is not None else ""


def once(handler):
    """``handler`` (a ClientApp's message handler), answering a copy of the message it
    answered last (same type and round) with the reply it gave, without running again."""

    @functools.wraps(handler)
    def answer(msg: Message, context: Context) -> Message:
        key, mark = _key(msg), context.state.config_records.get(_ANSWERED)
        if key and mark is not None and mark.get("key") == key:
            return Message(RecordDict({k[len(_ANSWER):]: v for k, v in context.state.items()
                                       if k.startswith(_ANSWER)}), reply_to=msg)
        reply = handler(msg, context)
        if not reply.has_error():
            for k in [k for k in context.state if k.startswith(_ANSWER)]:
                del context.state[k]
            for k, v in reply.content.items():
                context.state[_ANSWER + k] = v
            context.state[_ANSWERED] = ConfigRecord({"key": key})
        return reply

    return answer


def _restore(context: Context) -> tuple[Weights | None, Encoder | None]:
    """The model this rover holds and its uplink encoder (None before round 1)."""
    if _HELD not in context.state:
        return None, None
    held_record = context.state[_HELD]
    assert isinstance(held_record, ArrayRecord)  # written by _store
    held = {k: v.numpy() for k, v in held_record.items()}
    # the encoder is this rover's own state, written by this rover: unpickling is safe
    blob = context.state[_ENCODER]["pickle"]
    assert isinstance(blob, bytes)  # written by _store
    return held, pickle.loads(blob)


def _store(context: Context, held: Weights, encoder: Encoder) -> None:
    context.state[_HELD] = ArrayRecord({k: Array(np.ascontiguousarray(v)) for k, v in held.items()})
    context.state[_ENCODER] = ConfigRecord({"pickle": pickle.dumps(encoder)})


def _downlink(msg: Message) -> tuple[bytes, str, str]:
    """The downlink payload, its kind and the model version it is relative to."""
    config = msg.content["config"]
    return (from_record(msg.content.array_records.get("downlink")), str(config.get("downlink-kind", "none")),
            str(config.get("reference-version", "")))


def _reply(msg: Message, content: dict[str, ArrayRecord | MetricRecord | ConfigRecord], held: Weights) -> Message:
    """A reply that reports the version of the model this rover holds (what it trained from)."""
    content["state"] = ConfigRecord({"held-version": model_version(held)})
    return Message(RecordDict(content), reply_to=msg)


def _error_reply(msg: Message, metrics: dict, e: FedmapError, held: Weights | None = None) -> Message:
    """Reported, not raised: the base drops this rover for the round (a rejected update)
    or stops the run with this line (any other error)."""
    error: dict[str, ConfigRecordValues] = {"reason": str(e), "fatal": not isinstance(e, RejectedUpdate)}
    content: dict[str, ArrayRecord | MetricRecord | ConfigRecord] = {"metrics": MetricRecord(metrics),
                                                                     "error": ConfigRecord(error)}
    if held is None:
        return Message(RecordDict(content), reply_to=msg)
    return _reply(msg, content, held)


@app.train()
@once
def train(msg: Message, context: Context) -> Message:
    try:  # a bad run or node config is a mistake: reported as fatal, the base stops the run
        settings = RunSettings.from_run_config(dict(context.run_config))
        pid, local = load_local_map(dict(context.node_config))
    except FedmapError as e:
        return _error_reply(msg, {}, e)
    try:
        check_key(dict(context.node_config), msg.content["config"].get(KEY_ROVER))
    except FedmapError as e:  # not fatal to the run: the base refuses this rover, the others go on
        return _error_reply(msg, {"partition-id": pid}, RejectedUpdate(str(e)))
    try:
        held, encoder = rover_state(settings, local, *_restore(context))
    except FedmapError as e:
        return _error_reply(msg, {}, e)
    server_round = int(cast(int, msg.content["config"]["server-round"]))  # the base sends an int
    down, kind, reference = _downlink(msg)
    metrics: dict[str, MetricRecordValues] = {"partition-id": pid, "known-cells": local.n_known,
                                              "height": local.shape[0], "width": local.shape[1],
                                              "downlink-bytes": len(down)}
    try:
        held = receive(held, down, kind, reference)
    except FedmapError as e:  # e.g. a broadcast relative to a model it does not hold: keep what it has
        return _error_reply(msg, metrics, e, held)
    _store(context, held, encoder)
    try:
        payload, loss = train_round(settings, local, pid, server_round, held, encoder)
    except FedmapError as e:
        _store(context, held, encoder)
        return _error_reply(msg, metrics, e, held)
    _store(context, held, encoder)
    if "fault" in context.node_config:  # fault-injection tests only (fedmap rover --fault)
        payload = inject(str(context.node_config["fault"]), payload, server_round)
    metrics["uplink-bytes"] = len(payload)
    if loss is not None:
        metrics["loss"] = float(loss)
    return _reply(msg, {"uplink": to_record(payload), "metrics": MetricRecord(metrics)}, held)


@app.evaluate()
@once
def evaluate(msg: Message, context: Context) -> Message:
    """The final broadcast: decode it, keep it, optionally save it (node config ``out``)."""
    settings = RunSettings.from_run_config(dict(context.run_config))
    pid, local = load_local_map(dict(context.node_config))
    held, encoder = rover_state(settings, local, *_restore(context))
    down, kind, reference = _downlink(msg)
    held = receive(held, down, kind, reference)
    _store(context, held, encoder)
    out = context.node_config.get("out")
    if out:
        save_received(settings, local, held, Path(str(out)))
    done = context.node_config.get("done-file")
    if done:  # `fedmap rover` waits for this file to stop its SuperNode: the run is over for this rover
        atomic_write_bytes(Path(str(done)), str(context.run_id).encode())
    return _reply(msg, {"metrics": MetricRecord({"partition-id": pid, "downlink-bytes": len(down)})}, held)


def flwr_clientapp_main(argv: list[str]) -> None:
    """Flower's ``flwr-clientapp`` command with ``argv``, in this process (the warm
    ClientApp server's forked children, :mod:`fedmap.flower.warm`); exits like the command.
    Its module is imported with this one, so the warm server's children inherit it (it
    pulls in Flower's runtime API: FastAPI, SQLAlchemy, seconds of imports per message)."""
    import sys

    sys.argv = ["flwr-clientapp", *argv]
    flwr_clientapp()


def flower_superexec_main(argv: list[str]) -> None:
    """Flower's ``flower-superexec`` command with ``argv``, in this process (a warm server's
    forked child, :mod:`fedmap.flower.warm`): the SuperNode's SuperExec, which asks the
    SuperNode for each message's task and starts its ClientApp, without a fresh Python
    importing Flower's runtime again (1.5 s of CPU per rover)."""
    import sys

    sys.argv = ["flower-superexec", *argv]
    flower_superexec()
