"""Sharing without a base station: the strategies of the ``mesh`` and ``leader`` topologies.

The agents are the rovers (0, 1, ...) and, unless ``[link] lander_agent = false``, the
lander (:data:`~fedmap.mission.link.BASE`), an agent that never moves and observes
nothing. The mission loop (:mod:`fedmap.mission.sim`) decides who sends to whom each
round (every link that is up on a ``mesh``; member to leader and back on ``leader``) and
calls the same three hooks for every message: :meth:`PeerStrategy.peer_message` on the
sender, :meth:`~PeerStrategy.receive_peer` on the receiver and
:meth:`~PeerStrategy.peer_acked` on the sender when it arrived (the link-level
acknowledgement). :meth:`~PeerStrategy.peer_round` closes a round once its messages have
arrived.

* ``raw`` (:class:`RawGossip`): anti-entropy gossip of observed cells, coded with the
  ``context`` codec like ``raw`` on the star. Every agent keeps, per other agent, the
  cells it knows that agent holds (its version vector, kept per cell): those it sent and
  saw acknowledged, and those it received from it. A message carries every cell the sender
  holds that it does not know the receiver holds, so nothing is sent twice over a link that
  acknowledged it, and nothing is sent back to where it came from. Over budget, the newest
  cells that fit (as on the star); lost cells are sent again.
* ``gossip`` (:class:`ModelGossip`): decentralised averaging of the ``fedmap`` preset's
  network (DSGD-style). At each sync every rover trains its own model on its own map
  (``[strategies.gossip]`` sets the training, as for ``fedmap``), then sends it to each
  agent it exchanges with this round, coded with the preset's uplink codec *relative to the
  model of it the receiver last acknowledged* (the versions protocol per link: 8 bytes name
  that reference; a message against any other is rejected). Each agent then mixes what
  arrived with Metropolis weights (:func:`~fedmap.federation.aggregate.metropolis_mix`,
  coverage-aware like the preset's aggregator: a grid entry is averaged over the agents
  that trained it). A lost message leaves its weight with the receiver's own model.

* ``admm`` (:class:`Admm`): DiNNO's decentralised C-ADMM, the peers' baseline, on the same
  network, messages and versions protocol as ``gossip``, with dual variables per link.

Where there is no lander agent, the "global map" scored at every evaluation is the map
the whole team agrees on: each cell that every rover's belief holds with the same class
(UNKNOWN elsewhere).
"""

from __future__ import annotations

import struct
from collections.abc import Collection

import numpy as np

from fedmap.config import method_config
from fedmap.errors import RejectedUpdate
from fedmap.federation.aggregate import admm_consensus, metropolis_mix, metropolis_weight
from fedmap.federation.codecs import Encoder, decode
from fedmap.federation.mapcodec import decode_map, encode_map
from fedmap.federation.runner import agent_seed, init_held, model_version
from fedmap.maps.grid import UNKNOWN, GridMap, classes_from_rgb
from fedmap.mission.link import BASE
from fedmap.mission.strategies import (
    MISSION_DEFAULTS,
    Outgoing,
    Strategy,
    _cut_to_budget,
    pack_down,
    torch_threads,
    unpack_down,
)
from fedmap.nets.model import Weights, build_model, get_weights, render, set_weights
from fedmap.nets.training import fit
from fedmap.pipeline import initial_weights

Cell = tuple[int, int]
_MODEL = struct.Struct("<8sB")  # the reference model version (8 bytes), the sender's degree this round


class PeerStrategy(Strategy):
    """Base of the peer strategies: agent bookkeeping (index ``n`` is the lander)."""

    shares = True

    def __init__(self, truth: GridMap, team: list, budget: dict[str, int | None], *, base: Cell,
                 lander_agent: bool) -> None:
        super().__init__(truth, team, budget)
        self.n = len(team)
        self.base_cell = base
        self.lander_agent = lander_agent
        self.degree: dict[int, int] = {}

    def _i(self, agent: int) -> int:
        return self.n if agent == BASE else agent

    def _local(self, i: int) -> np.ndarray | None:
        return self.team[i].local if i < self.n else None

    def _agent_belief(self, i: int) -> np.ndarray:
        local, held = self._local(i), self._held_i(i)
        return held if local is None else np.where(local != UNKNOWN, local, held).astype(np.uint8)

    def _held_i(self, i: int) -> np.ndarray:
        raise NotImplementedError

    def held(self, k: int) -> np.ndarray:
        return self._held_i(k)

    def global_map(self) -> np.ndarray:
        """The lander's belief; without a lander agent, the cells every rover agrees on."""
        if self.lander_agent:
            return self._agent_belief(self.n)
        beliefs = [self._agent_belief(k) for k in range(self.n)]
        agree = np.all([b == beliefs[0] for b in beliefs[1:]], axis=0) if self.n > 1 else np.ones(self.shape, bool)
        return np.where(agree, beliefs[0], UNKNOWN).astype(np.uint8)

    def _reports(self, i: int) -> dict[int, tuple[Cell, Cell | None]]:
        """Every rover's position and target as agent ``i`` knows them (its own, now)."""
        known = dict(self.base_reports if i == self.n else self.known_reports[i])
        if i < self.n:
            known[i] = self._report(i)
        return known

    def _heard(self, i: int, reports: dict[int, tuple[Cell, Cell | None]]) -> None:
        target = self.base_reports if i == self.n else self.known_reports[i]
        target.update({k: v for k, v in reports.items() if k != i})

    # -- the hooks the mission loop calls
    def peer_links(self, round_no: int, pairs: list[tuple[int, int]]) -> None:
        """The exchanges of round ``round_no`` (undirected pairs of agents), before any message."""
        self.degree = {}
        for a, b in pairs:
            self.degree[a] = self.degree.get(a, 0) + 1
            self.degree[b] = self.degree.get(b, 0) + 1

    def peer_message(self, a: int, b: int, round_no: int, step: int, budget: int | None) -> Outgoing:
        raise NotImplementedError

    def receive_peer(self, b: int, a: int, payload: bytes, ctx: dict, round_no: int, step: int) -> bool:
        raise NotImplementedError

    def peer_acked(self, a: int, b: int, ctx: dict) -> None:
        pass

    def peer_round(self, round_no: int, agents: Collection[int] | None = None) -> None:
        """Close round ``round_no`` for ``agents`` (None: every agent) once their messages
        have arrived (on ``leader``: the leaders first, then their members)."""


class RawGossip(PeerStrategy):
    """Anti-entropy gossip of observed cells (see the module docstring)."""

    name = "raw"

    def __init__(self, truth: GridMap, team: list, budget: dict[str, int | None], *, base: Cell,
                 lander_agent: bool) -> None:
        super().__init__(truth, team, budget, base=base, lander_agent=lander_agent)
        m = self.n + 1
        self.hold = [np.full(self.shape, UNKNOWN, dtype=np.uint8) for _ in range(m)]  # cells received
        self.got = [np.full(self.shape, -1, dtype=np.int64) for _ in range(m)]  # step each was received
        self.has = [[np.zeros(self.shape, dtype=bool) for _ in range(m)] for _ in range(m)]  # i knows j holds
        #: every delivered message: (round, sender, receiver, flat indices of the cells it carried)
        self.deliveries: list[tuple[int, int, int, np.ndarray]] = []

    def _held_i(self, i: int) -> np.ndarray:
        return self.hold[i]

    def peer_message(self, a: int, b: int, round_no: int, step: int, budget: int | None) -> Outgoing:
        ia, ib = self._i(a), self._i(b)
        belief = self._agent_belief(ia)
        local = self._local(ia)
        stamps = self.got[ia] if local is None else np.where(local != UNKNOWN, self.team[ia].obs_step, self.got[ia])
        candidates = (belief != UNKNOWN) & ~self.has[ia][ib]
        reports = self._reports(ia)

        def make(mask: np.ndarray) -> bytes:
            return pack_down("map", "", reports, encode_map(np.where(mask, belief, UNKNOWN).astype(np.uint8)))

        payload, sent = _cut_to_budget(make, stamps, candidates, budget)
        return Outgoing(payload, "cells", {"sent": sent})

    def receive_peer(self, b: int, a: int, payload: bytes, ctx: dict, round_no: int, step: int) -> bool:
        ia, ib = self._i(a), self._i(b)
        _, _, reports, body = unpack_down(payload)
        cells = decode_map(body, expected_shape=self.shape)
        carried = cells != UNKNOWN
        new = carried & (self.hold[ib] == UNKNOWN)
        self.hold[ib][new] = cells[new]  # observations are truth: they never conflict
        self.got[ib][new] = step
        self.has[ib][ia] |= carried  # the sender holds what it sent
        self._heard(ib, reports)
        self.deliveries.append((round_no, a, b, np.flatnonzero(carried)))
        return True

    def peer_acked(self, a: int, b: int, ctx: dict) -> None:
        self.has[self._i(a)][self._i(b)] |= ctx["sent"]


class ModelGossip(PeerStrategy):
    """Decentralised averaging of the ``fedmap`` network with Metropolis weights (see the
    module docstring)."""

    name = "gossip"

    def __init__(self, truth: GridMap, team: list, budget: dict[str, int | None], *, base: Cell,
                 lander_agent: bool, settings: dict, seed: int) -> None:
        super().__init__(truth, team, budget, base=base, lander_agent=lander_agent)
        pc = method_config("fedmap", **{**MISSION_DEFAULTS["fedmap"], **settings, "seed": seed})
        self.fed = pc.federation
        self.codec = self.fed.uplink
        self.coverage = self.fed.aggregator == "coverage"
        self.init = init_held(initial_weights(pc, self.shape[0]))
        self.model = build_model(pc.model.network(self.shape[0]))
        m = self.n + 1
        self.w: list[Weights] = [self.init for _ in range(m)]  # each agent's model
        self.ref: list[list[Weights]] = [[self.init] * m for _ in range(m)]  # i's model as i knows j holds it
        self.recv: list[list[Weights]] = [[self.init] * m for _ in range(m)]  # j's model as i holds it
        self.inbox: list[dict[int, tuple[Weights, int]]] = [{} for _ in range(m)]
        self.rendered: dict[str, np.ndarray] = {}
        self.rejected = 0

    def _held_i(self, i: int) -> np.ndarray:
        w = self.w[i]
        v = model_version(w)
        if v not in self.rendered:
            set_weights(self.model, w)
            with torch_threads():
                self.rendered[v] = classes_from_rgb(render(self.model, *self.shape))
        return self.rendered[v]

    def at_sync(self, round_no: int) -> None:
        """Every rover trains its own model on its own map, from the model it holds."""
        for k, r in enumerate(self.team):
            local = self.truth.with_classes(r.local, f"rover {k}")
            set_weights(self.model, self.w[k])
            with torch_threads():
                fit(self.model, local, self.fed.local, seed=agent_seed(self.fed.seed, round_no - 1, k))
            w = get_weights(self.model)
            if all(np.isfinite(v).all() for v in w.values()):  # a diverged fit is not shared
                self.w[k] = w

    def peer_message(self, a: int, b: int, round_no: int, step: int, budget: int | None) -> Outgoing:
        ia, ib = self._i(a), self._i(b)
        ref = self.ref[ia][ib]
        body = Encoder(self.codec).encode(self.w[ia], reference=ref)
        head = _MODEL.pack(bytes.fromhex(model_version(ref)), min(self.degree.get(a, 1), 255))
        payload = head + body
        if budget is not None and len(payload) > budget:
            return Outgoing(None, "model", {})
        return Outgoing(payload, "model", {"decoded": decode(body, reference=ref)})

    def receive_peer(self, b: int, a: int, payload: bytes, ctx: dict, round_no: int, step: int) -> bool:
        ia, ib = self._i(a), self._i(b)
        ref_version, degree = _MODEL.unpack_from(payload)
        held = self.recv[ib][ia]
        if ref_version.hex() != model_version(held):
            self.rejected += 1
            return False
        try:
            w = decode(payload[_MODEL.size:], reference=held)
        except RejectedUpdate:
            self.rejected += 1
            return False
        self.recv[ib][ia] = w
        self.inbox[ib][a] = (w, degree)
        return True

    def peer_acked(self, a: int, b: int, ctx: dict) -> None:
        self.ref[self._i(a)][self._i(b)] = ctx["decoded"]

    def _closing(self, agents: Collection[int] | None) -> list[int]:
        """The agents' indices (the lander is ``n``) that close their round now."""
        return [i for i in range(self.n + 1) if agents is None or (BASE if i == self.n else i) in agents]

    def peer_round(self, round_no: int, agents: Collection[int] | None = None) -> None:
        """Each closing agent mixes the models that arrived this round (Metropolis weights)."""
        new = list(self.w)
        for i in self._closing(agents):
            agent = BASE if i == self.n else i
            got, self.inbox[i] = self.inbox[i], {}
            if not got:
                continue
            mine = self.degree.get(agent, len(got))
            nbrs = [(w, metropolis_weight(mine, d)) for w, d in got.values()]
            new[i] = metropolis_mix(self.w[i], nbrs, untouched=self.init if self.coverage else None)
        self.w = new


#: C-ADMM's penalty parameter rho (DiNNO's): the weight of the pull towards each
#: neighbour, per squared parameter difference, against the map loss. The loss is a mean
#: over the map's known cells, so its gradient on one grid entry is of order 1 / cells, and
#: rho must be as small: measured on the ramen preset at 100 steps, rho = 1e-6 gave a belief
#: accuracy of 0.629 (1e-7: 0.627); 1e-5 to 0.3 gave 0.585-0.617, and on a 32² test map
#: rho >= 0.1 pinned every model to its start (nothing learned).
ADMM_RHO = 1e-6


class Admm(ModelGossip):
    """DiNNO's decentralised C-ADMM (Yu, Chung, Schwager 2022) on the ``fedmap`` network:
    the peers' baseline, with the same messages and versions protocol per link as
    :class:`ModelGossip`. At each sync every agent sends its model to the agents it exchanges
    with; once they arrived, agent i updates its dual variable per link,
    ``p_ij <- p_ij + rho (theta_i - theta_j)``, then takes its primal step: it trains on its
    own map from ``theta_i`` with the augmented Lagrangian
    ``loss_i(theta) + <theta, sum_j p_ij> + rho sum_j ||theta - (theta_i + theta_j) / 2||^2``
    (``rho`` = :data:`ADMM_RHO`). The lander, which has no map, takes the exact minimiser of
    its penalty. A link whose message was lost this round is left out of both steps."""

    name = "admm"

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.dual: dict[tuple[int, int], Weights] = {}  # (i, j): p_ij, per link, on agent i

    def at_sync(self, round_no: int) -> None:
        """Nothing before the messages: C-ADMM trains after it heard its neighbours."""

    def peer_round(self, round_no: int, agents: Collection[int] | None = None) -> None:
        """Each closing agent's dual and primal steps (a rover that heard nobody this round
        trains on its own map alone)."""
        rho = ADMM_RHO
        new = list(self.w)
        names = [n for n, _ in self.model.named_parameters()]
        for i in self._closing(agents):
            got, self.inbox[i] = self.inbox[i], {}
            mine = self.w[i]
            if not got and i == self.n:
                continue
            p_sum = {k: np.zeros_like(mine[k], dtype=np.float64) for k in names}
            mids = []
            for j, (wj, _) in sorted(got.items()):
                d = self.dual.setdefault((i, j), {k: np.zeros_like(mine[k], dtype=np.float64) for k in names})
                for k in names:
                    d[k] += rho * (mine[k].astype(np.float64) - wj[k])
                    p_sum[k] += d[k]
                mids.append({k: (mine[k].astype(np.float64) + wj[k]) / 2 for k in names})
            if i == self.n:  # no map: argmin <theta, p> + rho sum_j ||theta - m_j||^2, in closed form
                out = dict(mine)
                for k in names:
                    out[k] = admm_consensus(p_sum[k], [m[k] for m in mids], rho).astype(np.float32)
                new[i] = out
                continue
            new[i] = self._primal(i, round_no, p_sum, mids)
        self.w = new

    def _primal(self, i: int, round_no: int, p_sum: dict, mids: list[dict]) -> Weights:
        import torch  # the network's own library; imported here to keep the module's import light

        set_weights(self.model, self.w[i])
        params = dict(self.model.named_parameters())
        p_t = {k: torch.as_tensor(v, dtype=torch.float32) for k, v in p_sum.items()}
        m_t = [{k: torch.as_tensor(v, dtype=torch.float32) for k, v in m.items()} for m in mids]

        def penalty() -> torch.Tensor:
            total = torch.zeros(())
            for k, theta in params.items():
                total = total + (theta * p_t[k]).sum()
                for m in m_t:
                    total = total + ADMM_RHO * ((theta - m[k]) ** 2).sum()
            return total

        local = self.truth.with_classes(self.team[i].local, f"rover {i}")
        with torch_threads():
            fit(self.model, local, self.fed.local, seed=agent_seed(self.fed.seed, round_no - 1, i),
                penalty=penalty if mids else None)
        w = get_weights(self.model)
        return w if all(np.isfinite(v).all() for v in w.values()) else self.w[i]
