"""A site of the predictor's federated fine-tuning: a Flower ``ClientApp`` that fine-tunes
the global weights on the site's own samples; its maps never leave it.

Node config: ``partition-id`` (the site's index, which seeds its rounds) and ``samples``
(its fine-tuning samples, :func:`fedmap.training.predictorfed.save_site_samples`).
``query``: say which site it is. ``train``: decode the global weights, run
:func:`~fedmap.training.predictorfed.local_round` and reply with the new weights and the
site's sample count. ``evaluate``: the run is over; with ``done-file=<path>`` in the node
config it writes that file.
"""

from __future__ import annotations

from pathlib import Path

from flwr.app import ConfigRecord, Context, Message, MetricRecord, RecordDict
from flwr.clientapp import ClientApp

from fedmap._util import atomic_write_bytes
from fedmap.errors import FedmapError
from fedmap.federation.codecs import Encoder, decode
from fedmap.flower.polling import quick_pulls
from fedmap.flower.predictor.task import PredictorRun
from fedmap.flower.records import from_record, to_record
from fedmap.training.predictorfed import load_site_samples, local_round

app = ClientApp()
quick_pulls()


def _site(context: Context) -> int:
    k = context.node_config.get("partition-id")
    if isinstance(k, bool) or not isinstance(k, int) or k < 0:
        raise FedmapError(f"node config partition-id must be the site's index (an integer >= 0), got {k!r}")
    return k


@app.query()
def which(msg: Message, context: Context) -> Message:
    return Message(RecordDict({"config": ConfigRecord({"site": _site(context)})}), reply_to=msg)


@app.train()
def fine_tune(msg: Message, context: Context) -> Message:
    try:
        k = _site(context)
        run = PredictorRun.from_run_config(dict(context.run_config))
        beliefs, targets = load_site_samples(str(context.node_config.get("samples", "")))
        weights = decode(from_record(msg.content.array_records.get("weights")))
        r = int(msg.content["config"]["round"])  # type: ignore[arg-type]
        update = local_round(weights, beliefs, targets, run.training, round=r, site=k)
    except FedmapError as e:  # reported, not raised: the server stops the run with this line
        return Message(RecordDict({"error": ConfigRecord({"reason": str(e)})}), reply_to=msg)
    return Message(RecordDict({"update": to_record(Encoder("fp32").encode(update)),
                               "metrics": MetricRecord({"site": k, "count": len(beliefs)})}), reply_to=msg)


@app.evaluate()
def over(msg: Message, context: Context) -> Message:
    done = context.node_config.get("done-file")
    if done:
        atomic_write_bytes(Path(str(done)), str(context.run_id).encode())
    return Message(RecordDict({"config": ConfigRecord({"site": _site(context)})}), reply_to=msg)
