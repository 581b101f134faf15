"""A rover of a mission on processes: a Flower ``ClientApp`` that keeps its rover's node
(:class:`fedmap.mission.remote.RoverNode`: its world, its end, its clock) between messages.

``query``: say which rover it is (node config ``partition-id``). ``train``: the base's
order of a sync round; the rover drives to its step, syncs and replies with its report. A
damaged order is answered with ``error`` / ``corrupt`` (the base sends it again). The node
lives in ``context.state`` between messages, one per strategy, and is dropped when its
strategy's mission is over. ``evaluate``: the mission is over; with ``done-file=<path>`` in
the node config it writes that file (``fedmap rover`` then stops its SuperNode).
"""

from __future__ import annotations

from pathlib import Path

from flwr.app import ConfigRecord, Context, Message, RecordDict
from flwr.clientapp import ClientApp

from fedmap._util import atomic_write_bytes
from fedmap.errors import FedmapError
from fedmap.flower.mission_task import CorruptMessage, damaged, parse_mission_fault, rover_answer
from fedmap.flower.records import from_record, to_record
from fedmap.mission.remote import Order

app = ClientApp()

_NODE = "fedmap.mission."  # + strategy: the pickled RoverNode
_FAULTS = "fedmap.mission-faults"  # faults already injected


def _rover(context: Context) -> int:
    k = context.node_config.get("partition-id")
    if isinstance(k, bool) or not isinstance(k, int) or k < 0:
        raise FedmapError(f"node config partition-id must be the rover's index (an integer >= 0), got {k!r}")
    return k


@app.query()
def which(msg: Message, context: Context) -> Message:
    return Message(RecordDict({"config": ConfigRecord({"rover": _rover(context)})}), reply_to=msg)


@app.train()
def order(msg: Message, context: Context) -> Message:
    strategy = str(msg.content["config"]["strategy"])
    k = _rover(context)
    raw = from_record(msg.content.array_records.get("order"))
    key = _NODE + strategy
    blob = context.state[key]["pickle"] if key in context.state else None  # this rover's own state
    assert blob is None or isinstance(blob, bytes)
    try:
        report, blob = rover_answer(blob, str(context.run_config["mission"]), strategy, k, raw)
    except CorruptMessage as e:
        return Message(RecordDict({"error": ConfigRecord({"reason": str(e), "corrupt": True})}), reply_to=msg)
    except FedmapError as e:
        return Message(RecordDict({"error": ConfigRecord({"reason": str(e), "corrupt": False})}), reply_to=msg)
    done = Order.from_bytes(raw).finish
    if done:
        context.state.pop(key, None)
    else:
        context.state[key] = ConfigRecord({"pickle": blob})
    fault = context.node_config.get("fault")
    if fault:  # fault-injection tests only: damage one report, once
        _, at = parse_mission_fault(str(fault))
        seen = str(context.state[_FAULTS]["done"]) if _FAULTS in context.state else ""
        tag = f"{strategy}@{at};"
        if Order.from_bytes(raw).step == at and tag not in seen:
            context.state[_FAULTS] = ConfigRecord({"done": f"{seen}{tag}"})
            report = damaged(report)
    return Message(RecordDict({"report": to_record(report)}), reply_to=msg)


@app.evaluate()
def over(msg: Message, context: Context) -> Message:
    done = context.node_config.get("done-file")
    if done:  # `fedmap rover` waits for this file to stop its SuperNode: the mission is over for this rover
        atomic_write_bytes(Path(str(done)), str(context.run_id).encode())
    return Message(RecordDict({"config": ConfigRecord({"rover": _rover(context)})}), reply_to=msg)
