"""Flower's waits, shortened for missions: a mission sends a message to every rover at every
sync, so the seconds Flower 1.41 waits between polls are most of a round.

Flower pulls a message's objects with a backoff that starts at 1 s
(``flwr.supercore.constant.PULL_INITIAL_BACKOFF``): an object not stored yet at the first
try (the usual case right after a message is announced) costs a second per message, on the
rover (its ClientApp pulling its task) and on the base (pulling a reply).
:func:`quick_pulls` starts that backoff at ``first`` seconds instead, in this process.

:func:`exchange` is the round trip of a mission's and the predictor sites' base stations:
push the messages, pull the replies until all are in or the deadline has passed. Flower's
own grid pulls the body of a reply whose message reached the SuperLink with retries for up
to 2 hours (``PULL_MAX_TIME``), in practice until the SuperLink drops the sender's upload
session (180 s): a reply cut mid-upload would hold a round past its deadline. Here every
pull gives up at the deadline.

A pull that waits for a cut reply's body also holds back the replies that arrive whole
meanwhile: they are only pulled by a later poll, and a poll that ran to the deadline was the
last. So when the deadline passes with replies missing, :func:`exchange` takes one last look
(:data:`LAST_LOOK` s for each body still missing): a reply stored whole before the deadline
is never lost behind one cut on its link. (A loopback run that lost every reply of a round,
the clean link's too, though all were pushed within seconds, fits this mechanism.)

An instruction can be lost too: a rover's SuperNode whose pull of its message was cut on
the link never sees it, while the SuperLink has it for delivered (seen on a link reset every
2 s: one rover of four never received round 1's message, and the round waited out its
120 s deadline). With ``resend``, :func:`exchange` sends a message again, as a new message
to the same node, once it has waited :data:`RESEND_FACTOR` times as long as the slowest
reply so far took (at least :data:`RESEND_MIN` s) without a reply; the first reply to any
copy answers it; at most :data:`RESEND_MAX` copies of a message go. A reply cut on its way
up is sent again the same way: each poll's pulls
give up after that same patience (not the deadline), and a reply whose body did not come
(Flower's :data:`REPLY_LOST` error) has its message sent again at once; the error is kept
as that message's answer only if nothing better comes before the deadline. The receiver
must take a copy it already answered as the same message (the paper's ClientApp returns
the reply it gave, so its reply is uploaded again, nothing more).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from flwr.app import Message
from flwr.serverapp import Grid
from flwr.supercore.inflatable import inflatable_utils

#: Seconds before the first retry of an object pull (Flower's own: 1 s), and the cap (10 s).
FIRST_RETRY, RETRY_CAP = 0.02, 1.0


def quick_pulls(first: float = FIRST_RETRY, cap: float = RETRY_CAP) -> None:
    """Start Flower's object-pull backoff at ``first`` s, capped at ``cap`` s, in this process."""
    for fn in (inflatable_utils.pull_objects, inflatable_utils.pull_and_inflate_object_from_tree):
        kw = fn.__kwdefaults__
        assert kw is not None and "initial_backoff" in kw, f"Flower's {fn.__name__} changed"
        kw["initial_backoff"], kw["backoff_cap"] = first, cap


#: Seconds between a base station's polls for replies (Flower's ``send_and_receive``: 3 s). Each
#: poll costs the SuperLink and the ServerApp CPU: 0.02 s cost a loaded two-core machine more
#: than it saved (fedmap.flower.mission.deploy.LOCAL_POLL).
POLL = 0.05
#: Seconds the last look after a deadline gives each reply body still missing.
LAST_LOOK = 2.0
#: With ``resend``: a message unanswered for this many times the slowest reply so far is sent again ...
RESEND_FACTOR = 3.0
#: ... but never sooner than this many seconds after it was last sent ...
RESEND_MIN = 10.0
#: ... and at most this many copies of one message (by default: a node that is down would be sent
#: one every RESEND_MIN s, and run each when it came back).
RESEND_MAX = 3
#: Flower's error for a reply whose message reached the SuperLink but whose body did not.
REPLY_LOST = "Reply message objects are unavailable"
#: Seconds between calls of :func:`exchange`'s ``overdue`` (a mission's base asks, that often,
#: which rover process runs on the node of a rover still holding its order).
OVERDUE = 30.0


@contextmanager
def pulls_within(seconds: float) -> Iterator[None]:
    """Flower's object pulls started inside give up after ``seconds`` (its own: 2 h), in this
    process: the message then comes back as Flower's error "Reply message objects are
    unavailable" (a reply lost on the link), as when the upload session expires."""
    kw = inflatable_utils.pull_objects.__kwdefaults__
    assert kw is not None and "max_time" in kw, "Flower's pull_objects changed"
    before, kw["max_time"] = kw["max_time"], max(seconds, 0.0)
    try:
        yield
    finally:
        kw["max_time"] = before


def copy_of(msg: Message) -> Message:
    """A new instruction with ``msg``'s content, type, group and destination (a new ID)."""
    md = msg.metadata
    return Message(msg.content, dst_node_id=md.dst_node_id, message_type=md.message_type, group_id=md.group_id,
                   ttl=md.ttl)


def exchange(grid: Grid, msgs: list[Message], timeout: float, *, poll: float = POLL,
             overdue: Callable[[set[str]], set[str]] | None = None, resend: bool = False,
             on_resend: Callable[[list[Message]], None] | None = None, most: int = RESEND_MAX) -> list[Message]:
    """Push ``msgs``, then pull their replies every ``poll`` s until all are in or
    ``timeout`` s have passed; no pull outlasts the deadline (:func:`pulls_within`), and one
    last look after it takes the replies that arrived whole while a pull waited for a cut one.
    ``overdue``: called every :data:`OVERDUE` s with the IDs of the messages still
    unanswered; the IDs it returns are no longer waited for (and no pull outlasts
    :data:`OVERDUE`: a reply cut on the link comes back as Flower's :data:`REPLY_LOST` error
    then, not at the deadline). ``resend``: a message that
    goes unanswered much longer than the others took is sent again (the module's
    docstring), at most ``most`` times, and ``on_resend`` is called with the copies; one
    reply per message is returned (the first, to whichever copy)."""
    pushed = list(grid.push_messages(msgs))
    first_of = {i: i for i in pushed if i}  # any copy's ID -> the ID of the message it copies
    original = {i: m for i, m in zip(pushed, msgs) if i}
    start = time.monotonic()
    sent_at = dict.fromkeys(first_of, start)  # message -> when its last copy went out
    copies_of = dict.fromkeys(first_of, 0)  # message -> copies sent
    ids = set(first_of)  # the IDs still waited for (copies included)
    answered: set[str] = set()
    replies: list[Message] = []
    cut: dict[str, Message] = {}  # message -> Flower's error for a reply to it whose body did not come
    slowest: float | None = None
    t_end = start + timeout
    check = time.monotonic() + OVERDUE

    def patience() -> float:
        return max(RESEND_MIN, RESEND_FACTOR * (slowest if slowest is not None else time.monotonic() - start))

    def take(got: list[Message], *, final: bool = False) -> None:
        nonlocal ids
        for m in got:
            first = first_of.get(m.metadata.reply_to_message_id)
            if first is None or first in answered:
                continue  # a reply to a copy of a message already answered
            if resend and not final and m.has_error() and REPLY_LOST in (m.error.reason or ""):
                cut[first] = m  # its answer only if no copy's reply comes in time
                sent_at[first] = -math.inf  # sent again at once
                ids.discard(m.metadata.reply_to_message_id)
                continue
            answered.add(first)
            replies.append(m)
        ids = {i for i in ids if first_of[i] not in answered}

    while ids and (left := t_end - time.monotonic()) > 0:
        bound = min(left, patience()) if resend else left
        if overdue is not None:  # a pull that waits for a cut body must not hold back the next ask
            bound = min(bound, OVERDUE)
        with pulls_within(bound):
            got = list(grid.pull_messages(ids))
        if any(not m.has_error() for m in got):
            slowest = time.monotonic() - start
        take(got)
        if ids and overdue is not None and time.monotonic() >= check:
            gone = overdue(set(ids))
            ids -= gone
            answered.update(first_of[i] for i in gone)
            check = time.monotonic() + OVERDUE
        waiting = {first_of[i] for i in ids} | (cut.keys() - answered)
        if waiting and resend and (slowest is not None or cut):
            now, wait = time.monotonic(), patience()
            due = sorted(f for f in waiting if now - sent_at[f] >= wait and copies_of[f] < most)
            if due:
                copies = [copy_of(original[f]) for f in due]
                for f, new in zip(due, grid.push_messages(copies)):
                    sent_at[f] = now
                    copies_of[f] += 1
                    if new:
                        first_of[new] = f
                        ids.add(new)
                if on_resend is not None:
                    on_resend(copies)
        if ids:
            time.sleep(poll)
    if ids:  # the deadline passed: what arrived whole while the last pull waited for a cut body
        with pulls_within(LAST_LOOK):
            take(list(grid.pull_messages(ids)), final=True)
    replies += [m for f, m in cut.items() if f not in answered]  # a reply cut, and no copy answered in time
    return replies
