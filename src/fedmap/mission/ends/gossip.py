"""``gossip`` and ``admm``: a network shared peer to peer, one :class:`GossipPeer` (or
:class:`AdmmPeer`) per agent.

* ``gossip``: decentralised averaging of the ``fedmap`` preset's network (DSGD-style). At
  each sync every rover trains its own model on its own map (``[strategies.gossip]`` sets
  the training, as for ``fedmap``), then sends it to each agent it exchanges with this
  round, coded with the preset's uplink codec *relative to the model of it the receiver
  last acknowledged* (the versions protocol per link: 8 bytes name that reference; a
  message against any other is rejected). Each agent then mixes what arrived with
  Metropolis weights (:func:`~fedmap.federation.aggregate.metropolis_mix`, coverage-aware
  like the preset's aggregator: a grid entry is averaged over the agents that trained it).
  A lost message leaves its weight with the receiver's own model.
* ``admm``: DiNNO's decentralised C-ADMM, the peers' baseline, on the same network,
  messages and versions protocol as ``gossip``, with dual variables per link.
"""

from __future__ import annotations

import struct
from typing import Any

import numpy as np

from fedmap.config import PipelineConfig
from fedmap.errors import RejectedUpdate
from fedmap.federation.aggregate import admm_consensus, metropolis_mix, metropolis_weight
from fedmap.federation.codecs import Encoder, decode
from fedmap.federation.runner import agent_seed, model_version
from fedmap.maps.grid import GridMap, classes_from_rgb
from fedmap.mission.ends.protocol import Cell, Journal, Outgoing, PeerEnd, torch_threads
from fedmap.nets.model import Weights, build_model, get_weights, render, set_weights
from fedmap.nets.training import fit

_MODEL = struct.Struct("<8sB")  # the reference model version (8 bytes), the sender's degree this round


class GossipPeer(PeerEnd):
    """An agent's end of ``gossip``: its model, and per other agent the model it knows that
    agent holds of it and the model it holds of that agent."""

    def __init__(self, agent: int, rover: Any, shape: tuple[int, int], starts: list[Cell], *, truth: GridMap,
                 pc: PipelineConfig, init: Weights, agents: tuple[int, ...], journal: Journal) -> None:
        super().__init__(agent, rover, shape, starts)
        self.truth, self.fed, self.init, self.journal = truth, pc.federation, init, journal
        self.codec = self.fed.uplink
        self.coverage = self.fed.aggregator == "coverage"
        self.model = build_model(pc.model.network(shape[0]))
        self.w: Weights = init  # its model
        self.ref = {j: init for j in agents}  # its model as it knows agent j holds it
        self.recv = {j: init for j in agents}  # agent j's model as it holds it
        self.inbox: dict[int, tuple[Weights, int]] = {}
        self.rendered: dict[str, np.ndarray] = {}
        self._decoded: dict[tuple[int, int], Weights] = {}  # (receiver, round) -> what a message in flight gives it

    def held(self) -> np.ndarray:
        v = model_version(self.w)
        if v not in self.rendered:
            set_weights(self.model, self.w)
            with torch_threads():
                self.rendered[v] = classes_from_rgb(render(self.model, *self.shape))
        return self.rendered[v]

    def _local(self) -> GridMap:
        return self.truth.with_classes(self.rover.local, f"rover {self.agent}")

    def at_sync(self, round_no: int) -> None:
        """A rover trains its own model on its own map, from the model it holds."""
        if self.rover is None:
            return
        set_weights(self.model, self.w)
        with torch_threads():
            fit(self.model, self._local(), self.fed.local, seed=agent_seed(self.fed.seed, round_no - 1, self.agent))
        w = get_weights(self.model)
        if all(np.isfinite(v).all() for v in w.values()):  # a diverged fit is not shared
            self.w = w

    def message(self, to: int, round_no: int, step: int, budget: int | None) -> Outgoing:
        ref = self.ref[to]
        body = Encoder(self.codec).encode(self.w, reference=ref)
        head = _MODEL.pack(bytes.fromhex(model_version(ref)), min(self.degree or 1, 255))
        payload = head + body
        if budget is not None and len(payload) > budget:
            return Outgoing(None, "model")
        self._decoded[to, round_no] = decode(body, reference=ref)
        return Outgoing(payload, "model")

    def receive(self, frm: int, payload: bytes, round_no: int, step: int) -> bool:
        ref_version, degree = _MODEL.unpack_from(payload)
        held = self.recv[frm]
        if ref_version.hex() != model_version(held):
            self.journal.rejected += 1
            return False
        try:
            w = decode(payload[_MODEL.size:], reference=held)
        except RejectedUpdate:
            self.journal.rejected += 1
            return False
        self.recv[frm] = w
        self.inbox[frm] = (w, degree)
        return True

    def delivered(self, to: int, round_no: int, ok: bool) -> None:
        decoded = self._decoded.pop((to, round_no), None)
        if ok and decoded is not None:
            self.ref[to] = decoded

    def close_round(self, round_no: int) -> None:
        """It mixes the models that arrived this round (Metropolis weights)."""
        got, self.inbox = self.inbox, {}
        if not got:
            return
        mine = self.degree or len(got)
        nbrs = [(w, metropolis_weight(mine, d)) for w, d in got.values()]
        self.w = metropolis_mix(self.w, nbrs, untouched=self.init if self.coverage else None)


#: C-ADMM's penalty parameter rho (DiNNO's): the weight of the pull towards each
#: neighbour, per squared parameter difference, against the map loss. The loss is a mean
#: over the map's known cells, so its gradient on one grid entry is of order 1 / cells, and
#: rho must be as small: measured on the ramen preset at 100 steps, rho = 1e-6 gave a belief
#: accuracy of 0.629 (1e-7: 0.627); 1e-5 to 0.3 gave 0.585-0.617, and on a 32² test map
#: rho >= 0.1 pinned every model to its start (nothing learned).
ADMM_RHO = 1e-6


class AdmmPeer(GossipPeer):
    """DiNNO's decentralised C-ADMM (Yu, Chung, Schwager 2022) on the ``fedmap`` network:
    the peers' baseline, with the same messages and versions protocol per link as
    :class:`GossipPeer`. At each sync every agent sends its model to the agents it exchanges
    with; once they arrived, agent i updates its dual variable per link,
    ``p_ij <- p_ij + rho (theta_i - theta_j)``, then takes its primal step: it trains on its
    own map from ``theta_i`` with the augmented Lagrangian
    ``loss_i(theta) + <theta, sum_j p_ij> + rho sum_j ||theta - (theta_i + theta_j) / 2||^2``
    (``rho`` = :data:`ADMM_RHO`). The lander, which has no map, takes the exact minimiser of
    its penalty. A link whose message was lost this round is left out of both steps."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.dual: dict[int, Weights] = {}  # j: p_ij, per link

    def at_sync(self, round_no: int) -> None:
        """Nothing before the messages: C-ADMM trains after it heard its neighbours."""

    def close_round(self, round_no: int) -> None:
        """Its dual and primal steps (a rover that heard nobody this round trains on its own
        map alone)."""
        rho = ADMM_RHO
        names = [n for n, _ in self.model.named_parameters()]
        got, self.inbox = self.inbox, {}
        mine = self.w
        if not got and self.rover is None:
            return
        p_sum = {k: np.zeros_like(mine[k], dtype=np.float64) for k in names}
        mids = []
        for j, (wj, _) in sorted(got.items()):
            d = self.dual.setdefault(j, {k: np.zeros_like(mine[k], dtype=np.float64) for k in names})
            for k in names:
                d[k] += rho * (mine[k].astype(np.float64) - wj[k])
                p_sum[k] += d[k]
            mids.append({k: (mine[k].astype(np.float64) + wj[k]) / 2 for k in names})
        if self.rover is None:  # no map: argmin <theta, p> + rho sum_j ||theta - m_j||^2, in closed form
            out = dict(mine)
            for k in names:
                out[k] = admm_consensus(p_sum[k], [m[k] for m in mids], rho).astype(np.float32)
            self.w = out
            return
        self.w = self._primal(round_no, p_sum, mids)

    def _primal(self, round_no: int, p_sum: dict, mids: list[dict]) -> Weights:
        import torch  # the network's own library; imported here to keep the module's import light

        set_weights(self.model, self.w)
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

        with torch_threads():
            fit(self.model, self._local(), self.fed.local, seed=agent_seed(self.fed.seed, round_no - 1, self.agent),
                penalty=penalty if mids else None)
        w = get_weights(self.model)
        return w if all(np.isfinite(v).all() for v in w.values()) else self.w
