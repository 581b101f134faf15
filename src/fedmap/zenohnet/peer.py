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
  (``fedmap/<team>/base/finished``). It gives no orders: the rounds run among the agents.
* **A rover** (``fedmap node peer``) asks the lander for the plan and the mission, waits
  for every agent to be up (liveliness ``fedmap/<team>/alive/peer/<agent>``), runs each
  strategy and writes its own log (its rover's steps and its
  :class:`~fedmap.mission.network.nodelog.PeerRecord`).

Faults: a damaged mail is refused by its check and sent again (a line of the run's faults);
an agent that leaves the team mid-mission (its liveliness token goes) stops the mission
with one line naming it: a lockstep round cannot close without it.
"""

from __future__ import annotations

import hashlib
import json
import queue
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from fedmap.errors import FedmapError
from fedmap.flower.checkpoint import run_dir
from fedmap.flower.mission.task import base_dir, damaged, log_dir, parse_mission_fault
from fedmap.mission.network.link import BASE
from fedmap.mission.network.nodelog import write_log
from fedmap.mission.network.peers import (
    MAIL_WAIT,
    Inbox,
    Mail,
    ProcessPeer,
    agents_of,
    peer_deployable,
    peer_strategies,
)
from fedmap.mission.network.wire import CorruptMessage
from fedmap.mission.scoring import mission_from_text, write_run
from fedmap.zenohnet.session import alive_key, mission_key

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


def finished_key(team: str) -> str:
    return f"fedmap/{team}/base/finished"


class Roster:
    """Which agents of team ``team`` are up, from their liveliness tokens. An agent never
    seen counts as alive (it may not have started yet); one seen and gone does not."""

    def __init__(self, session: Any, team: str) -> None:
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

        self.sub = session.liveliness().declare_subscriber(alive_key(team, "peer/*"), Callback(on, lambda: None),
                                                           history=True)

    def is_alive(self, agent: int) -> bool:
        name = agent_name(agent)
        with self.lock:
            return name in self.alive or name not in self.seen

    def wait_for(self, agents: list[int] | tuple[int, ...], timeout: float,
                 watch: Callable[[], None] | None = None) -> None:
        """Until every one of ``agents`` is up; one line naming those that are not after
        ``timeout`` s (``watch`` is called while it waits)."""
        t_end = time.monotonic() + timeout
        while True:
            if watch is not None:
                watch()
            with self.lock:
                missing = [a for a in agents if agent_name(a) not in self.alive]
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
                 fault: int | None = None, faults: list[dict] | None = None, timeout: float = MAIL_WAIT) -> None:
        from zenoh.handlers import Callback

        self.session, self.team, self.me, self.strategy, self.roster = session, team, me, strategy, roster
        self.fault, self.faults = fault, faults if faults is not None else []
        self.inbox = Inbox(alive=roster.is_alive, timeout=timeout, failed=lambda: self.error)
        self.timeout = timeout
        self.error: FedmapError | None = None
        self.out: queue.Queue = queue.Queue()
        self.queryable = session.declare_queryable(mail_key(team, strategy, me, "*"), Callback(self._take, lambda: None))
        self.thread = threading.Thread(target=self._send_all, name=f"mail-{agent_name(me)}", daemon=True)
        self.thread.start()

    def _take(self, query: Any) -> None:
        try:
            try:
                mail = Mail.from_bytes(query.payload.to_bytes() if query.payload is not None else b"")
            except CorruptMessage as e:
                query.reply_err(json.dumps({"reason": str(e), "corrupt": True}))
                return
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


def _ask(session: Any, key: str, payload: bytes, timeout: float, what: str) -> str:
    t_end = time.monotonic() + timeout
    while True:
        for reply in session.get(key, payload=payload, timeout=5.0):
            if reply.ok is not None:
                return reply.ok.payload.to_string()
            raise FedmapError(f"the lander refused: {reply.err.payload.to_string()}")
        if time.monotonic() > t_end:
            raise FedmapError(f"no lander answered for {what} within {timeout:g} s")
        time.sleep(0.2)


def _stepper(on_step: Callable[[str, int], None] | None, name: str) -> Callable[[int], None] | None:
    return None if on_step is None else (lambda t: on_step(name, t))


def serve_peer(session: Any, team: str, k: int, state: Path, *, connect_timeout: float = 300.0,
               fault: str | None = None, on_step: Callable[[str, int], None] | None = None) -> list[str]:
    """Rover ``k``'s agent of team ``team``: the plan and mission from the lander, every
    strategy run with the other agents, its own log in ``state``/log. The strategies run."""
    step = parse_mission_fault(fault)[1] if fault else None
    roster = Roster(session, team)
    token = session.liveliness().declare_token(alive_key(team, f"peer/{k}"))
    try:
        plan = json.loads(_ask(session, plan_key(team), b"", connect_timeout, "the plan"))
        text = _ask(session, mission_key(team), plan["mission"].encode(), connect_timeout, "the mission")
        mission = mission_from_text(text, frames=1)
        agents = [int(a) for a in plan["agents"]]
        if k not in agents:
            raise FedmapError(f"rover {k} is not in the team's agents {', '.join(map(agent_name, agents))}")
        log_dir(state).mkdir(parents=True, exist_ok=True)
        for name in plan["strategies"]:
            faults: list[dict] = []
            post = ZenohPost(session, team, k, name, roster, fault=step, faults=faults)
            try:
                roster.wait_for(agents, connect_timeout)
                peer = ProcessPeer(mission, name, k, post, mission_id=plan["mission"])
                record = peer.run(_stepper(on_step, name))
            finally:
                post.close()
            step = None  # (the fault: once)
            for entry in peer.log:
                write_log(log_dir(state), entry)
            write_log(log_dir(state), record)
            _ask(session, finished_key(team), json.dumps({"strategy": name, "agent": k, "faults": faults}).encode(),
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

    served = [session.declare_queryable(k, Callback(desk, lambda: None))
              for k in (plan_key(team), mission_key(team), finished_key(team))]
    roster = Roster(session, team)
    token = session.liveliness().declare_token(alive_key(team, "peer/lander")) if BASE in agents else None
    try:
        roster.wait_for(rovers, connect_timeout, watch)  # every rover up (or one line naming those that are not)
        if on_started is not None:
            on_started()
        for name in names:
            if BASE in agents:
                post = ZenohPost(session, team, BASE, name, roster, faults=faults)
                try:
                    record = ProcessPeer(mission, name, BASE, post, mission_id=mid).run(_stepper(on_step, name))
                finally:
                    post.close()
                write_log(base_dir(out), record)
            with cond:
                while finished[name] != set(rovers):
                    gone = [a for a in rovers if a not in finished[name] and not roster.is_alive(a)]
                    if gone:
                        raise FedmapError(f"{name}: rover {gone[0]} left the team before it finished")
                    if watch is not None:
                        watch()
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
