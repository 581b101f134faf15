"""A peer mission on Zenoh: one node per agent, no base station giving orders.

Every agent runs its side of the topology's rounds (:class:`~fedmap.mission.network.peers.ProcessPeer`),
and its :class:`~fedmap.mission.network.peers.Mail` travels as Zenoh queries
(:class:`ZenohPost`): to ``fedmap/<team>/peer/<to>/mail/<strategy>/<from>``, answered by
the receiver's queryable once the mail is in its inbox (so a mail is delivered, or sent
again: a damaged one fails its check and the receiver says so). Agents are named ``0, 1,
...`` (rovers) and ``lander``.

* **The lander** (``fedmap node base`` with a mesh or leader mission, or ``fedmap mission
  --deploy zenoh``) is the team's Zenoh router: it listens, and with certificates checks
  every node's TLS certificate and enforces access control (:func:`~fedmap.zenohnet.session.acl`:
  rover ``k`` may post mail only as itself, and receive only its own). It serves the
  mission (``fedmap/<team>/base/mission``) and the plan (``fedmap/<team>/base/plan``: the
  mission's id, its strategies and its agents), runs the lander's own agent when it is one
  (``[link] lander_agent``), and writes the run's files once every rover said it finished
  (``fedmap/<team>/base/finished/<k>``). It gives no orders: the rounds run among the agents.
* **A rover** (``fedmap node peer``) asks the lander for the plan and the mission, waits
  for every agent to be up (liveliness ``fedmap/<team>/alive/peer/<agent>``), runs each
  strategy and writes its own log (its rover's steps and its
  :class:`~fedmap.mission.network.nodelog.PeerRecord`).

At each sync a rover posts its cell to the lander's tables (``fedmap/<team>/base/table/...``)
and gets the round's table back: every rover's cell, and who left.

Faults: a damaged mail is refused by its check and sent again (a line of the run's faults);
an agent that leaves the team mid-mission (its liveliness token goes) is dropped by the next
round's table, alike for everyone: the team goes on without it (a line of the run's faults).
"""

from __future__ import annotations

import hashlib
import json
import os
import queue
import signal
import struct
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from fedmap.errors import FedmapError
from fedmap.flower.checkpoint import run_dir
from fedmap.flower.mission.task import base_dir, damaged, log_dir
from fedmap.mission.network.link import BASE
from fedmap.mission.network.nodelog import write_log
from fedmap.mission.network.peers import (
    MAIL_WAIT,
    POS,
    Inbox,
    Mail,
    ProcessPeer,
    Table,
    Tables,
    agents_of,
    peer_deployable,
    peer_strategies,
    pos_body,
)
from fedmap.mission.network.wire import CorruptMessage
from fedmap.mission.scoring import mission_from_text, write_run
from fedmap.zenohnet.session import alive_key, mission_key

Cell = tuple[int, int]
#: Seconds a sender waits for one reply to a mail before it asks again.
MAIL_REPLY = 5.0
#: Times a mail is sent again after its receiver found it damaged, before the mission fails.
MAIL_RESENDS = 3


def agent_name(a: int) -> str:
    return "lander" if a == BASE else str(a)


def mail_key(team: str, strategy: str, to: int, frm: int | str) -> str:
    """Where agent ``frm`` posts mail to agent ``to`` (``frm`` ``"*"``: the receiver's queryable)."""
    return f"fedmap/{team}/peer/{agent_name(to)}/mail/{strategy}/{frm if frm == '*' else agent_name(int(frm))}"


def plan_key(team: str) -> str:
    return f"fedmap/{team}/base/plan"


def finished_key(team: str, k: int | str) -> str:
    """Where rover ``k`` says it finished a strategy (``k`` ``"*"``: the lander's queryable)."""
    return f"fedmap/{team}/base/finished/{k}"


def table_key(team: str, strategy: str, k: int | str) -> str:
    """Where rover ``k`` posts its cell at a sync and gets the round's table back (``k`` ``"*"``: the lander's queryable)."""
    return f"fedmap/{team}/base/table/{strategy}/{k}"


def _mail_of(query: Any) -> Mail | None:
    """The mail a query carries; None, the query answered with an error and dropped, when
    its check fails (the sender sends it again)."""
    try:
        return Mail.from_bytes(query.payload.to_bytes() if query.payload is not None else b"")
    except CorruptMessage as e:
        query.reply_err(json.dumps({"reason": str(e), "corrupt": True}))
        query.drop()
        return None


class Desk:
    """The lander's tables of a peer mission (:class:`~fedmap.mission.network.peers.Tables`)
    served over Zenoh: a rover's query carries its cell (a checked :class:`Mail`) and is
    answered once the round's table is made (every rover posted or left)."""

    def __init__(self, tables: Tables, team: str) -> None:
        self.tables, self.team = tables, team
        self.pending: list[tuple[Any, str, int]] = []
        self.lock = threading.Lock()

    def take(self, query: Any) -> None:
        mail = _mail_of(query)
        if mail is None:
            return
        if str(query.key_expr) != table_key(self.team, mail.strategy, mail.sender) or len(mail.body) != 4:
            query.reply_err(json.dumps({"reason": f"a cell of rover {mail.sender} posted as {query.key_expr}"}))
            query.drop()
            return
        r, c = struct.unpack_from("<hh", mail.body)
        self.tables.post(mail.strategy, mail.step, mail.sender, (r, c))
        with self.lock:
            self.pending.append((query, mail.strategy, mail.step))
        self.settle()

    def settle(self) -> None:
        """Answer every query whose table is made (a rover posted, or one left)."""
        with self.lock, self.tables.cond:
            still = []
            for query, strategy, step in self.pending:
                table = self.tables.ready(strategy, step)
                if table is None:
                    still.append((query, strategy, step))
                    continue
                query.reply(query.key_expr, json.dumps({"cells": [list(c) for c in table[0]],
                                                        "gone": sorted(table[1])}))
                query.drop()
            self.pending = still
            self.tables.cond.notify_all()


class Roster:
    """Which agents of team ``team`` are up, from their liveliness tokens. An agent never
    seen counts as alive (it may not have started yet); one seen and gone does not."""

    def __init__(self, session: Any, team: str, on_change: Callable[[], None] | None = None) -> None:
        from zenoh import SampleKind
        from zenoh.handlers import Callback

        self.seen: set[str] = set()
        self.alive: set[str] = set()
        self.lock = threading.Lock()

        def on(sample: Any) -> None:
            name = str(sample.key_expr).rsplit("/", 1)[1]
            with self.lock:
                if sample.kind == SampleKind.PUT:
                    self.seen.add(name)
                    self.alive.add(name)
                else:
                    self.alive.discard(name)
            if on_change is not None:
                on_change()

        self.sub = session.liveliness().declare_subscriber(alive_key(team, "peer/*"), Callback(on, lambda: None),
                                                           history=True)

    def is_alive(self, agent: int) -> bool:
        name = agent_name(agent)
        with self.lock:
            return name in self.alive or name not in self.seen

    def wait_for(self, agents: list[int] | tuple[int, ...], timeout: float,
                 watch: Callable[[], None] | None = None) -> None:
        """Until every one of ``agents`` is up (or has left: it does not come back); one line
        naming those that are not after ``timeout`` s (``watch`` is called while it waits)."""
        t_end = time.monotonic() + timeout
        while True:
            if watch is not None:
                watch()
            with self.lock:
                missing = [a for a in agents if agent_name(a) not in self.alive | self.seen]
            if not missing:
                return
            if time.monotonic() > t_end:
                raise FedmapError(f"agent(s) {', '.join(agent_name(a) for a in missing)} did not come up within "
                                  f"{timeout:g} s")
            time.sleep(0.05)

    def close(self) -> None:
        self.sub.undeclare()


class ZenohPost:
    """Agent ``me``'s :class:`~fedmap.mission.network.peers.Post` for strategy ``strategy``
    on team ``team`` over ``session``: its queryable takes its mail (checked: a damaged one
    is refused, the sender sends it again; one from another agent than its key says is
    refused), a thread of its own sends its mail, in order. ``fault``: ``corrupt@STEP``
    damages its first mail of step STEP once (tests). ``faults``: where the lines of what
    went wrong go."""

    def __init__(self, session: Any, team: str, me: int, strategy: str, roster: Roster, *,
                 fault: int | None = None, faults: list[dict] | None = None, timeout: float = MAIL_WAIT,
                 tables: Tables | None = None) -> None:
        from zenoh.handlers import Callback

        self.session, self.team, self.me, self.strategy, self.roster = session, team, me, strategy, roster
        self.fault, self.faults = fault, faults if faults is not None else []
        self.tables = tables  # the lander's own (its agent asks them here); a rover asks the lander
        self.inbox = Inbox(alive=roster.is_alive, timeout=timeout, failed=lambda: self.error)
        self.timeout = timeout
        self.error: FedmapError | None = None
        #: what it posted: mails delivered and their bytes (framing included; a copy sent again counts again)
        self.sent = {"mails": 0, "mail_bytes": 0}
        self.out: queue.Queue = queue.Queue()
        self.queryable = session.declare_queryable(mail_key(team, strategy, me, "*"), Callback(self._take, lambda: None))
        self.thread = threading.Thread(target=self._send_all, name=f"mail-{agent_name(me)}", daemon=True)
        self.thread.start()

    def _take(self, query: Any) -> None:
        mail = _mail_of(query)
        if mail is None:
            return
        try:
            frm = str(query.key_expr).rsplit("/", 1)[1]
            if agent_name(mail.sender) != frm or mail.to != self.me or mail.strategy != self.strategy:
                query.reply_err(json.dumps({"reason": f"mail from {agent_name(mail.sender)} to {agent_name(mail.to)} "
                                                      f"({mail.strategy}) posted as {frm}"}))
                return
            self.inbox.put(mail)
            query.reply(query.key_expr, b"")
        finally:
            query.drop()

    def send(self, mail: Mail) -> None:
        if self.error is not None:
            raise self.error
        self.out.put(mail)

    def wait(self, key: tuple[int, int, int, int]) -> Mail:
        return self.inbox.wait(key)

    def table(self, strategy: str, step: int, agent: int, pos: Cell | None) -> Table:
        if self.tables is not None:
            return self.tables.table(strategy, step, agent, pos)
        assert pos is not None  # (a rover's: the lander keeps the tables itself)
        mail = Mail(POS, agent, BASE, 0, step, 0, strategy, pos_body(pos))
        text = _ask(self.session, table_key(self.team, strategy, agent), mail.to_bytes(), self.timeout,
                    f"the table of step {step}", reply_timeout=self.timeout)
        got = json.loads(text)
        return [(int(c[0]), int(c[1])) for c in got["cells"]], frozenset(int(a) for a in got["gone"])

    def _send_all(self) -> None:
        while True:
            mail = self.out.get()
            if mail is None:
                return
            try:
                self._send(mail)
            except FedmapError as e:
                self.error = e
                return

    def _send(self, mail: Mail) -> None:
        key, raw = mail_key(self.team, self.strategy, mail.to, self.me), mail.to_bytes()
        if self.fault is not None and mail.step == self.fault:
            self.fault = None  # a test's fault: this mail damaged on the way, once
            raw = damaged(raw)
        t_end, damages = time.monotonic() + self.timeout, 0
        while True:
            ok, err = False, None
            for reply in self.session.get(key, payload=raw, timeout=MAIL_REPLY):
                if reply.ok is not None:
                    ok = True
                else:
                    err = reply.err.payload.to_string()
            if ok or err is not None:
                self.sent["mails"] += 1
                self.sent["mail_bytes"] += len(raw)
            if ok:
                return
            who = f"{self.strategy} agent {agent_name(mail.to)}"
            if err is not None:
                why = json.loads(err)
                if not why.get("corrupt"):
                    raise FedmapError(f"{who} refused mail of step {mail.step}: {why.get('reason')}")
                damages += 1
                self.faults.append({"strategy": self.strategy, "rover": self.me,
                                    "fault": f"mail to {agent_name(mail.to)} at step {mail.step} damaged on the way "
                                             f"({why.get('reason')}); sent again"})
                if damages > MAIL_RESENDS:
                    raise FedmapError(f"every copy of a mail to {who} was damaged ({damages})")
                raw = mail.to_bytes()
                continue
            if not self.roster.is_alive(mail.to):
                raise FedmapError(f"{who} left the team: its mail of step {mail.step} cannot be delivered")
            if time.monotonic() > t_end:
                raise FedmapError(f"{who} took no mail for {self.timeout:g} s")
            time.sleep(0.02)  # its queryable is not there yet (it is still on its previous strategy)

    def close(self) -> None:
        """Once every mail it posted is delivered."""
        self.out.put(None)
        self.thread.join()
        self.queryable.undeclare()
        if self.error is not None:
            raise self.error


def _ask(session: Any, key: str, payload: bytes, timeout: float, what: str, reply_timeout: float = 5.0) -> str:
    t_end = time.monotonic() + timeout
    while True:
        for reply in session.get(key, payload=payload, timeout=reply_timeout):
            if reply.ok is not None:
                return reply.ok.payload.to_string()
            raise FedmapError(f"the lander refused: {reply.err.payload.to_string()}")
        if time.monotonic() > t_end:
            raise FedmapError(f"no lander answered for {what} within {timeout:g} s")
        time.sleep(0.2)


def _stepper(on_step: Callable[[str, int], None] | None, name: str) -> Callable[[int], None] | None:
    return None if on_step is None else (lambda t: on_step(name, t))


def parse_peer_fault(text: str | None) -> tuple[str, int] | None:
    """A test's fault of a peer node: ``corrupt@STEP`` damages its first mail of STEP once;
    ``die@STEP`` kills its process (SIGKILL) at STEP, of its first strategy."""
    if not text:
        return None
    kind, _, at = text.partition("@")
    if kind not in ("corrupt", "die") or not at.isdigit():
        raise FedmapError(f"unknown peer fault {text!r}: use corrupt@STEP or die@STEP")
    return kind, int(at)


def serve_peer(session: Any, team: str, k: int, state: Path, *, connect_timeout: float = 300.0,
               fault: str | None = None, on_step: Callable[[str, int], None] | None = None) -> list[str]:
    """Rover ``k``'s agent of team ``team``: the plan and mission from the lander, every
    strategy run with the other agents, its own log in ``state``/log (written as it goes).
    The strategies run."""
    hurt = parse_peer_fault(fault)
    roster = Roster(session, team)
    token = session.liveliness().declare_token(alive_key(team, f"peer/{k}"))
    try:
        plan = json.loads(_ask(session, plan_key(team), b"", connect_timeout, "the plan"))
        text = _ask(session, mission_key(team), plan["mission"].encode(), connect_timeout, "the mission")
        mission = mission_from_text(text, frames=1)
        agents = [int(a) for a in plan["agents"]]
        if k not in agents:
            raise FedmapError(f"rover {k} is not in the team's agents {', '.join(map(agent_name, agents))}")
        folder = log_dir(state)
        folder.mkdir(parents=True, exist_ok=True)
        for name in plan["strategies"]:
            faults: list[dict] = []
            post = ZenohPost(session, team, k, name, roster, faults=faults,
                             fault=hurt[1] if hurt and hurt[0] == "corrupt" else None)

            def stepped(t: int, name: str = name) -> None:
                if hurt is not None and hurt[0] == "die" and t == hurt[1]:
                    os.kill(os.getpid(), signal.SIGKILL)  # a test's fault: killed mid-mission
                if on_step is not None:
                    on_step(name, t)

            try:
                roster.wait_for(agents, connect_timeout)
                peer = ProcessPeer(mission, name, k, post, mission_id=plan["mission"])
                record = peer.run(stepped, keep=lambda entry: write_log(folder, entry))
            finally:
                post.close()
            hurt = None  # (a fault: once)
            record.wire.update(post.sent)  # the mail it posted (all delivered: the post is closed)
            write_log(folder, record)
            _ask(session, finished_key(team, k), json.dumps({"strategy": name, "agent": k, "faults": faults}).encode(),
                 connect_timeout, "the end of the mission")
        return list(plan["strategies"])
    finally:
        token.undeclare()
        roster.close()


def mission_id(text: str) -> str:
    """A peer mission's id: its resolved TOML's hash (every agent of it names its logs by it)."""
    return hashlib.sha256(text.encode()).hexdigest()[:12]


def run_lander(session: Any, team: str, mission_text: str, *, out: Path, strategies: tuple[str, ...] = (),
               connect_timeout: float = 300.0, frames: int = 60,
               on_step: Callable[[str, int], None] | None = None,
               watch: Callable[[], None] | None = None,
               on_started: Callable[[], None] | None = None) -> list[str]:
    """The lander of a peer mission over ``session`` (module docstring): the mission's
    desk, its own agent when it is one (its record in ``<out>.run/base/``), the run's files
    once every rover finished every strategy. ``watch`` is called while it waits (a
    launcher's check on its rover processes); ``on_started()`` once every rover is up. The strategies run."""
    from zenoh.handlers import Callback

    t0 = time.perf_counter()
    out = Path(out)
    run_dir(out).mkdir(parents=True, exist_ok=True)
    mission = mission_from_text(mission_text, frames=frames)
    c = mission.config
    names = strategies or peer_strategies(c)[0]
    peer_deployable(c, names)  # the topology and the strategies
    mid = mission_id(mission_text)
    agents = agents_of(c, mission.base)
    rovers = [a for a in agents if a != BASE]
    plan = json.dumps({"mission": mid, "strategies": list(names), "agents": list(agents)})
    finished: dict[str, set[int]] = {n: set() for n in names}
    faults: list[dict] = []
    cond = threading.Condition()

    def desk(query: Any) -> None:
        try:
            key = str(query.key_expr)
            body = query.payload.to_string() if query.payload is not None else ""
            if key == plan_key(team):
                query.reply(query.key_expr, plan)
            elif key == mission_key(team):
                if body == mid:
                    query.reply(query.key_expr, mission_text)
                else:
                    query.reply_err(f"no mission {body!r} (this team's is {mid})")
            else:
                try:
                    note = json.loads(body)
                    if key != finished_key(team, int(note["agent"])):
                        query.reply_err(f"rover {note['agent']}'s end posted as {key}")
                        return
                    with cond:
                        finished[str(note["strategy"])].add(int(note["agent"]))
                        faults.extend(dict(f) for f in note.get("faults", ()))
                        cond.notify_all()
                except (ValueError, KeyError, TypeError) as e:
                    query.reply_err(f"not a finished note ({type(e).__name__})")
                    return
                query.reply(query.key_expr, b"")
        finally:
            query.drop()

    gone_noted: set[int] = set()

    def tabled(strategy: str, step: int, gone: frozenset[int]) -> None:  # a round's table is made
        if on_step is not None and BASE not in agents:  # (the lander's own agent reports its steps)
            on_step(strategy, step)
        for a in sorted(gone - gone_noted):
            gone_noted.add(a)
            faults.append({"strategy": strategy, "rover": a, "fault": f"left the team before the sync of step "
                           f"{step}; the team went on without it (its last record stands)"})

    roster: Roster | None = None
    tables = Tables(c.rovers, alive=lambda a: roster is None or roster.is_alive(a), timeout=MAIL_WAIT,
                    on_table=tabled)
    keeper = Desk(tables, team)
    served = [session.declare_queryable(k, Callback(desk, lambda: None))
              for k in (plan_key(team), mission_key(team), finished_key(team, "*"))]
    served.append(session.declare_queryable(table_key(team, "*", "*"), Callback(keeper.take, lambda: None)))
    roster = Roster(session, team, on_change=keeper.settle)
    token = session.liveliness().declare_token(alive_key(team, "peer/lander")) if BASE in agents else None
    try:
        roster.wait_for(rovers, connect_timeout, watch)  # every rover up (or one line naming those that are not)
        if on_started is not None:
            on_started()
        for name in names:
            if BASE in agents:
                post = ZenohPost(session, team, BASE, name, roster, faults=faults, tables=tables)
                try:
                    record = ProcessPeer(mission, name, BASE, post, mission_id=mid).run(_stepper(on_step, name))
                finally:
                    post.close()
                record.wire.update(post.sent)
                write_log(base_dir(out), record)
            with cond:  # every rover finished, or left the team
                while finished[name] | {a for a in rovers if not roster.is_alive(a)} != set(rovers):
                    if watch is not None:
                        watch()
                    keeper.settle()
                    cond.wait(0.2)
            if on_step is not None:
                on_step(name, c.steps)
    finally:
        if token is not None:
            token.undeclare()
        roster.close()
        for q in served:
            q.undeclare()
    write_run(run_dir(out), mission_text, names, time.perf_counter() - t0, faults, mission_id=mid)
    return list(names)


__all__ = ["MAIL_REPLY", "MAIL_RESENDS", "Roster", "ZenohPost", "agent_name", "finished_key", "mail_key",
           "mission_id", "plan_key", "run_lander", "serve_peer"]
