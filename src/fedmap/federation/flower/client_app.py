"""The rover: a Flower ``ClientApp`` that trains on its own local map.

Each ``train`` message carries the base station's downlink payload (empty in round 1:
every rover rebuilds the initial model from the shared seed, as in the in-process
runner). The rover decodes it relative to the model it holds, runs
:func:`~fedmap.federation.runner.rover_step` and replies with its uplink payload and its
number of known cells. What the rover holds between rounds (the decoded global model and
its uplink encoder with the error-feedback residual) lives in ``context.state``.

The final ``evaluate`` message delivers the last global model; with ``out=<dir>`` in the
node config the rover saves it there with its rendering.
"""

from __future__ import annotations

import pickle

import numpy as np
from flwr.app import Array, ArrayRecord, ConfigRecord, Context, Message, MetricRecord, RecordDict
from flwr.clientapp import ClientApp

from fedmap.comm import Encoder, decode
from fedmap.errors import FedmapError
from fedmap.federation.flower.records import from_record, to_record
from fedmap.federation.flower.settings import RunSettings, load_local_map
from fedmap.federation.runner import rover_step
from fedmap.model import Weights, build_model, get_weights, preset

app = ClientApp()

_HELD, _ENCODER = "fedmap.held", "fedmap.encoder"


def _restore(context: Context, settings: RunSettings, height: int) -> tuple[Weights, Encoder]:
    """The model this rover holds and its uplink encoder (fresh in round 1)."""
    if _HELD in context.state:
        held = {k: v.numpy() for k, v in context.state[_HELD].items()}
        # the encoder is this rover's own state, written by this rover: unpickling is safe
        encoder = pickle.loads(context.state[_ENCODER]["pickle"])
        return held, encoder
    from fedmap.pipeline import initial_model

    net = preset(settings.net, height)
    model = initial_model(net, init=settings.init, seed=settings.federation.seed, prior_steps=settings.prior_steps)
    return get_weights(model), Encoder(settings.federation.uplink)


def _store(context: Context, held: Weights, encoder: Encoder) -> None:
    context.state[_HELD] = ArrayRecord({k: Array(np.ascontiguousarray(v)) for k, v in held.items()})
    context.state[_ENCODER] = ConfigRecord({"pickle": pickle.dumps(encoder)})


@app.train()
def train(msg: Message, context: Context) -> Message:
    settings = RunSettings.from_run_config(dict(context.run_config))
    pid, local = load_local_map(dict(context.node_config))
    server_round = int(msg.content["config"]["server-round"])
    held, encoder = _restore(context, settings, local.shape[0])
    down = from_record(msg.content.array_records.get("downlink"))
    if down:  # the broadcast of the previous round, relative to what this rover holds
        held = decode(down, reference=held)
    metrics = {"partition-id": pid, "known-cells": local.n_known, "height": local.shape[0], "width": local.shape[1],
               "downlink-bytes": len(down)}
    model = build_model(preset(settings.net, local.shape[0]))
    try:
        payload, loss = rover_step(model, local, held, encoder, settings.federation, round_idx=server_round - 1,
                                   agent=pid)
    except FedmapError as e:  # reported, not raised: the base records why this rover dropped out
        _store(context, held, encoder)
        return Message(RecordDict({"metrics": MetricRecord(metrics), "error": ConfigRecord({"reason": str(e)})}),
                       reply_to=msg)
    _store(context, held, encoder)
    metrics["uplink-bytes"] = len(payload)
    if loss is not None:
        metrics["loss"] = float(loss)
    return Message(RecordDict({"uplink": to_record(payload), "metrics": MetricRecord(metrics)}), reply_to=msg)


@app.evaluate()
def receive_global(msg: Message, context: Context) -> Message:
    """The final broadcast: decode it, keep it, optionally save it (node config ``out``)."""
    settings = RunSettings.from_run_config(dict(context.run_config))
    pid, local = load_local_map(dict(context.node_config))
    held, encoder = _restore(context, settings, local.shape[0])
    down = from_record(msg.content.array_records.get("downlink"))
    held = decode(down, reference=held)
    _store(context, held, encoder)
    out = context.node_config.get("out")
    if out:
        from pathlib import Path

        from fedmap.maps.grid import classes_from_rgb
        from fedmap.maps.io import save_map
        from fedmap.model import render, save_model, set_weights

        model = build_model(preset(settings.net, local.shape[0]))
        set_weights(model, held)
        save_model(model, Path(str(out)) / "global_model.safetensors")
        rgb = render(model, *local.shape)
        save_map(local.with_classes(classes_from_rgb(rgb), "global map received by the rover"),
                 Path(str(out)) / "global_map.png")
    return Message(RecordDict({"metrics": MetricRecord({"partition-id": pid, "downlink-bytes": len(down)})}),
                   reply_to=msg)
