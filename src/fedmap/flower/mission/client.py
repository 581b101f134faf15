"""A rover of a mission on processes: a Flower ``ClientApp`` that keeps its rover's node
(:class:`fedmap.mission.network.remote.ProcessRover`: its world, its end, its clock) between messages.

``query``: say which rover it is (node config ``partition-id``) and which rover process
(node config ``boot``: a rover killed and started again with its registered key is the same
node, and only this tells the base that the order its old process took will not be answered). ``train``: the base's
order of a sync round; the rover drives to its step, syncs and replies with its report. A
damaged order is answered with ``error`` / ``corrupt`` (the base sends it again). The node
lives in the rover's own folder between messages (node config ``state-dir``), one per
mission and strategy (:func:`fedmap.flower.mission.task.rover_answer`), so a rover
process killed and started again carries on. A rover that lost that folder answers
``error`` / ``lost``; the base sends the order again with every order it sent before
(``history``), and the rover rebuilds its node from them. ``evaluate``: the mission is over; with ``done-file=<path>`` in
the node config it writes that file (``fedmap rover`` then stops its SuperNode).
"""

from __future__ import annotations

from pathlib import Path

from flwr.app import ConfigRecord, Context, Message, RecordDict
from flwr.clientapp import ClientApp

from fedmap._util import atomic_write_bytes
from fedmap.errors import FedmapError
from fedmap.flower.mission.task import CorruptMessage, LostState, damaged, node_feed, parse_mission_fault, rover_answer
from fedmap.flower.polling import quick_pulls
from fedmap.flower.records import from_record, to_record
from fedmap.flower.task import KEY_ROVER, check_key
from fedmap.mission.network.remote import Order

app = ClientApp()
quick_pulls()  # a round is a message per rover: Flower's 1 s first retry would be most of it



def _rover(context: Context) -> int:
    k = context.node_config.get("partition-id")
    if isinstance(k, bool) or not isinstance(k, int) or k < 0:
        raise FedmapError(f"node config partition-id must be the rover's index (an integer >= 0), got {k!r}")
    return k


def _boot(context: Context) -> str:
    """Which rover process runs this node (node config ``boot``, set by ``fedmap rover``; "" without)."""
    return str(context.node_config.get("boot", ""))


@app.query()
def which(msg: Message, context: Context) -> Message:
    try:
        check_key(dict(context.node_config), msg.content["config"].get(KEY_ROVER))
    except FedmapError as e:
        return _error(msg, str(e), corrupt=False)
    return Message(RecordDict({"config": ConfigRecord({"rover": _rover(context), "boot": _boot(context)})}),
                   reply_to=msg)


@app.train()
def order(msg: Message, context: Context) -> Message:
    k = _rover(context)
    state = context.node_config.get("state-dir")
    if not state:
        return _error(msg, "node config state-dir (where the rover keeps its state) is missing", corrupt=False)
    raw = from_record(msg.content.array_records.get("order"))
    history = msg.content.array_records.get("history")  # sent with the order to a rover that lost its state
    try:
        report = rover_answer(Path(str(state)), str(context.run_config["mission"]), k, raw,
                              feed=node_feed(dict(context.node_config)),
                              history=None if history is None else from_record(history))
    except CorruptMessage as e:
        return _error(msg, str(e), corrupt=True)
    except LostState as e:
        return _error(msg, str(e), corrupt=False, lost=True)
    except FedmapError as e:
        return _error(msg, str(e), corrupt=False)
    fault = context.node_config.get("fault")
    if fault:  # fault-injection tests only: damage one report, once
        _, at = parse_mission_fault(str(fault))
        order = Order.from_bytes(raw)
        mark = Path(str(state)) / f"fault-{order.mission}-{order.strategy}-{at}"
        if order.step == at and not mark.exists():
            atomic_write_bytes(mark, b"")
            report = damaged(report)
    return Message(RecordDict({"report": to_record(report), "config": ConfigRecord({"boot": _boot(context)})}),
                   reply_to=msg)


def _error(msg: Message, reason: str, *, corrupt: bool, lost: bool = False) -> Message:
    """Reported, not raised: a damaged order is sent again, a rover that lost its state gets its
    orders again, any other error stops the run with this line."""
    return Message(RecordDict({"error": ConfigRecord({"reason": reason, "corrupt": corrupt, "lost": lost})}),
                   reply_to=msg)


@app.evaluate()
def over(msg: Message, context: Context) -> Message:
    done = context.node_config.get("done-file")
    if done:  # `fedmap rover` waits for this file to stop its SuperNode: the mission is over for this rover
        atomic_write_bytes(Path(str(done)), str(context.run_id).encode())
    return Message(RecordDict({"config": ConfigRecord({"rover": _rover(context)})}), reply_to=msg)
