"""The server of the predictor's federated fine-tuning: a Flower ``ServerApp`` that runs
FedAvg rounds over one SuperNode per site.

It asks every connected node which site it is (a ``query``; node config ``partition-id``),
then every round sends every site the global weights (a ``train`` message: a fedmap
``fp32`` payload, :mod:`fedmap.flower.records`) and averages the sites' replies in site
order with :func:`fedmap.training.predictorfed.fedavg_predictor`: the same weights as
:func:`~fedmap.training.predictorfed.federate`. A site that does not answer within
``deadline`` fails the run (FedAvg over the sites that answered would not be the
comparison it is measured against). At the end every site gets an ``evaluate`` message
(its SuperNode may stop). Files: :mod:`fedmap.flower.predictor.task`.
"""

from __future__ import annotations

import time
from logging import INFO

from flwr.app import ConfigRecord, Context, Message, MessageType, RecordDict
from flwr.serverapp import Grid, ServerApp
from flwr.supercore import log

from fedmap.errors import FedmapError
from fedmap.federation.codecs import Encoder, decode
from fedmap.flower.polling import exchange, quick_pulls
from fedmap.flower.predictor.task import PredictorRun, save_round, write_rounds_log
from fedmap.flower.records import check_flower_count, from_record, to_record
from fedmap.flower.task import write_status
from fedmap.training.predictorfed import fedavg_predictor

app = ServerApp()
quick_pulls()


def _connect(grid: Grid, run: PredictorRun) -> dict[int, int]:
    """``{site: node}`` once every site has said which it is, within ``connect_timeout``."""
    t_end = time.monotonic() + run.connect_timeout
    node_of: dict[int, int] = {}
    while len(node_of) < run.sites and time.monotonic() < t_end:
        new = sorted(set(grid.get_node_ids()) - set(node_of.values()))
        msgs = [Message(RecordDict({"config": ConfigRecord({})}), dst_node_id=n, message_type=MessageType.QUERY)
                for n in new]
        sent = {m.object_id: n for m, n in zip(msgs, new)}
        for reply in exchange(grid, msgs, min(run.deadline, 60.0)) if msgs else []:
            if reply.has_error() or "config" not in reply.content.config_records:
                continue
            k = int(reply.content["config"]["site"])  # type: ignore[arg-type]
            if not 0 <= k < run.sites:
                raise FedmapError(f"a node says it is site {k}; the run's sites are 0..{run.sites - 1}")
            node_of[k] = sent[reply.metadata.reply_to_message_id]
        if len(node_of) < run.sites:
            time.sleep(0.5)
    missing = sorted(set(range(run.sites)) - set(node_of))
    if missing:
        raise FedmapError(f"site(s) {missing} did not connect within {run.connect_timeout:g} s")
    return node_of


def run_predictor_base(grid: Grid, run: PredictorRun) -> None:
    write_status(run.out, "running", message="waiting for the sites")
    node_of = _connect(grid, run)
    held = run.initial_weights()
    log_rounds: dict = {"sites": run.sites, "rounds": [], "counts": {}}
    for r in range(1, run.rounds + 1):
        t0 = time.perf_counter()
        down = Encoder("fp32").encode(held)
        msgs, sent = [], {}
        for k in range(run.sites):
            rec = to_record(down)
            flower_down = check_flower_count(rec, len(down))
            m = Message(RecordDict({"weights": rec, "config": ConfigRecord({"round": r})}), dst_node_id=node_of[k],
                        message_type=MessageType.TRAIN)
            msgs.append(m)
            sent[m.object_id] = k
        updates, counts, up_bytes = {}, {}, {}
        for reply in exchange(grid, msgs, run.deadline):
            site = sent.get(reply.metadata.reply_to_message_id)
            if site is None or reply.has_error():
                continue
            if "error" in reply.content.config_records:
                raise FedmapError(f"site {site}: {reply.content['error']['reason']!s}")
            payload = from_record(reply.content.array_records.get("update"))
            updates[site] = decode(payload)
            counts[site] = float(reply.content["metrics"]["count"])  # type: ignore[arg-type]
            up_bytes[site] = len(payload)
        missing = sorted(set(range(run.sites)) - set(updates))
        if missing:
            raise FedmapError(f"round {r}: site(s) {missing} did not answer within {run.deadline:g} s")
        held = fedavg_predictor([updates[k] for k in range(run.sites)], [counts[k] for k in range(run.sites)])
        save_round(run.out, r, held)
        log_rounds["counts"] = {str(k): counts[k] for k in range(run.sites)}
        log_rounds["rounds"].append({"round": r, "seconds": time.perf_counter() - t0, "downlink_bytes": len(down),
                                     "downlink_flower_bytes": flower_down,
                                     "uplink_bytes": {str(k): up_bytes[k] for k in range(run.sites)}})
        write_rounds_log(run.out, log_rounds)
        write_status(run.out, "running", round=r, rounds=run.rounds)
        log(INFO, "fedmap: predictor round %d of %d: %d sites in %.1f s", r, run.rounds, run.sites,
            time.perf_counter() - t0)
    exchange(grid, [Message(RecordDict({"config": ConfigRecord({"done": True})}), dst_node_id=n,
                            message_type=MessageType.EVALUATE) for n in node_of.values()], 60)


@app.main()
def main(grid: Grid, context: Context) -> None:
    run = PredictorRun.from_run_config(dict(context.run_config))
    try:
        run_predictor_base(grid, run)
    except Exception as e:  # the command that started the run waits on the status file: never leave it "running"
        msg = str(e) if isinstance(e, FedmapError) else f"{type(e).__name__}: {e}".splitlines()[0]
        write_status(run.out, "failed", message=msg)
        log(INFO, "fedmap: error: %s", msg)
        raise
    write_status(run.out, "done", round=run.rounds, rounds=run.rounds)
