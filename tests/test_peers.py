"""Teams without a base station and teams with a helicopter: the mesh and leader topologies,
gossip, Metropolis averaging and the helicopter's flight rule, each against an independent
reference (brute force, scipy's graph routines, a matrix power, a hand computation)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components, shortest_path

from conftest import maze
from fedmap.errors import FedmapError
from fedmap.federation.aggregate import metropolis_mix, metropolis_weight
from fedmap.maps.grid import FREE, IMPASSABLE, UNKNOWN
from fedmap.mission import LinkConfig, MissionConfig
from fedmap.mission.network.link import BASE, PEER, Link
from fedmap.mission.network.topology import MeshTopology, components, elect_leaders, route
from fedmap.mission.settings import HelicopterConfig
from fedmap.mission.sim import run_mission
from fedmap.mission.world.sensing import block_classes, coarse_footprint


def _random_graph(rng, n: int, p: float) -> list[tuple[int, int]]:
    agents = [BASE, *range(n - 1)]
    return [(a, b) for a, b in itertools.combinations(agents, 2) if rng.random() < p]


# -- Metropolis averaging ---------------------------------------------------------------------

@pytest.mark.parametrize("seed", range(4))
def test_metropolis_gossip_on_a_perfect_link_converges_to_the_plain_average(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(3, 7))
    ring = [(i, (i + 1) % n) for i in range(n)]  # connected
    extra = [(a, b) for a, b in itertools.combinations(range(n), 2) if rng.random() < 0.3]
    edges = sorted({tuple(sorted(e)) for e in ring + extra})
    deg = [sum(i in e for e in edges) for i in range(n)]
    w = [{"a": rng.normal(size=(3, 2)).astype(np.float32), "b": rng.normal(size=5).astype(np.float32)}
         for _ in range(n)]
    # the mixing matrix, built independently, as the reference for one step
    W = np.zeros((n, n))
    for a, b in edges:
        W[a, b] = W[b, a] = 1 / (1 + max(deg[a], deg[b]))
    W += np.diag(1 - W.sum(axis=1))
    x = np.stack([np.concatenate([v["a"].ravel(), v["b"]]) for v in w]).astype(np.float64)
    want_mean = x.mean(axis=0)
    for it in range(300):
        nbrs = {i: [j for a, b in edges for j in ((b,) if a == i else (a,) if b == i else ())] for i in range(n)}
        w = [metropolis_mix(w[i], [(w[j], metropolis_weight(deg[i], deg[j])) for j in nbrs[i]]) for i in range(n)]
        if it == 0:
            got = np.stack([np.concatenate([v["a"].ravel(), v["b"]]) for v in w])
            np.testing.assert_allclose(got, W @ x, rtol=1e-5, atol=1e-6)
    final = np.stack([np.concatenate([v["a"].ravel(), v["b"]]) for v in w])
    for row in final:
        np.testing.assert_allclose(row, want_mean, atol=1e-4)


def test_coverage_aware_mixing_by_hand():
    init = {"g": np.zeros(4, dtype=np.float32)}
    own = {"g": np.array([0.0, 2.0, 0.0, 4.0], dtype=np.float32)}  # touched entries 1 and 3
    nb = {"g": np.array([6.0, 0.0, 0.0, 8.0], dtype=np.float32)}  # touched entries 0 and 3
    out = metropolis_mix(own, [(nb, 0.25)], untouched=init)["g"]
    # entry 0: only the neighbour touched it -> its value; 1: only itself -> its value;
    # 2: nobody -> its own; 3: both -> (0.75 * 4 + 0.25 * 8) / 1
    np.testing.assert_allclose(out, [6.0, 2.0, 0.0, 0.75 * 4 + 0.25 * 8])
    plain = metropolis_mix(own, [(nb, 0.25)])["g"]
    np.testing.assert_allclose(plain, 0.75 * own["g"] + 0.25 * nb["g"])
    with pytest.raises(FedmapError):
        metropolis_mix(own, [(nb, 0.7), (nb, 0.7)])


# -- groups, leaders, routes ------------------------------------------------------------------

@pytest.mark.parametrize("seed", range(8))
def test_groups_leaders_and_routes_against_scipy(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(2, 9))
    agents = [BASE, *range(n - 1)]
    pairs = _random_graph(rng, n, float(rng.uniform(0.1, 0.6)))
    idx = {a: i for i, a in enumerate(agents)}
    adj = np.zeros((n, n))
    for a, b in pairs:
        adj[idx[a], idx[b]] = adj[idx[b], idx[a]] = 1
    _, labels = connected_components(csr_matrix(adj), directed=False)
    groups = components(agents, pairs)
    for g in groups:
        assert len({labels[idx[a]] for a in g}) == 1
    assert sum(len(g) for g in groups) == n and len(groups) == len(set(labels))
    leaders = elect_leaders(groups)
    for g in groups:
        want = BASE if BASE in g else min(g)
        assert all(leaders[a] == want for a in g)
    # deterministic: the same groups and leaders whatever order the agents and links come in
    for _ in range(5):
        shuffled = [pairs[i] for i in rng.permutation(len(pairs))]
        swapped = [(b, a) if rng.random() < 0.5 else (a, b) for a, b in shuffled]
        order = [agents[i] for i in rng.permutation(n)]
        assert elect_leaders(components(order, swapped)) == leaders
    hops = shortest_path(csr_matrix(adj), unweighted=True, directed=False)
    for a, b in itertools.permutations(agents, 2):
        r = route(a, b, pairs)
        if not np.isfinite(hops[idx[a], idx[b]]):
            assert r is None
            continue
        assert r is not None and r[0] == a and r[-1] == b and len(r) - 1 == hops[idx[a], idx[b]]
        assert all(tuple(sorted(e)) in {tuple(sorted(p)) for p in pairs} for e in zip(r, r[1:]))


def test_mesh_topology_against_brute_force():
    rng = np.random.default_rng(3)
    for _ in range(30):
        base = (int(rng.integers(0, 50)), int(rng.integers(0, 50)))
        positions = [(int(r), int(c)) for r, c in rng.integers(0, 50, size=(int(rng.integers(1, 6)), 2))]
        pr = float(rng.uniform(3, 30))
        for lander in (True, False):
            topo = MeshTopology(base, pr, lander)
            ags = ([BASE] if lander else []) + list(range(len(positions)))

            def pos(a, positions=positions, base=base):
                return base if a == BASE else positions[a]

            want = [(a, b) for a, b in itertools.combinations(ags, 2)
                    if np.hypot(pos(a)[0] - pos(b)[0], pos(a)[1] - pos(b)[1]) <= pr]
            assert topo.pairs(positions) == want


def test_link_drops_are_seeded_per_link_and_round_and_the_lander_cut_holds():
    cfg = LinkConfig(drop=0.5, seed=4, lander_cut=(20, 40))
    link = Link(cfg, MeshTopology((0, 0)))
    draws = [[link.down(r, a, b) for r in range(200)] for a, b in [(BASE, 0), (0, 1), (1, 2)]]
    again = Link(cfg, MeshTopology((0, 0)))
    assert draws == [[again.down(r, a, b) for r in range(200)] for a, b in [(BASE, 0), (0, 1), (1, 2)]]
    assert link.down(3, 1, 0) == link.down(3, 0, 1)  # a link, not a direction
    share = np.mean(draws)
    assert 0.4 < share < 0.6
    assert draws[0] != draws[1]  # independent links
    assert all(link.down(r, BASE, 0, step=s) for r in range(10) for s in range(20, 40))
    assert not any(link.down(r, 0, 1, step=25) != link.down(r, 0, 1) for r in range(50))  # only the lander's


# -- missions -----------------------------------------------------------------------------------

def _mission(**kw) -> MissionConfig:
    link = kw.pop("link", {})
    heli = kw.pop("helicopter", None)
    base = dict(rovers=3, steps=60, sync_every=5, speed=1, sensor_radius=3.0, eval_pairs=8,
                strategies=("none", "raw", "central"))
    return MissionConfig(**{**base, **kw}, link=LinkConfig(**link),
                         **({"helicopter": heli} if heli is not None else {}))


@pytest.mark.parametrize("link", [dict(topology="mesh", loss=0.3, drop=0.3, peer_range=12.0),
                                  dict(topology="mesh", loss=0.2, lander_agent=False, latency=1),
                                  dict(topology="leader", loss=0.3, drop=0.2, peer_range=10.0, uplink_bytes=60)])
def test_gossip_delivers_every_cell_once_per_acknowledged_link(link):
    truth = maze(32, seed=2)
    res = run_mission(_mission(link=link, strategies=("raw",)), truth)
    run = res.runs["raw"]
    s = run.sharing
    assert s is not None and s.journal.deliveries, "no gossip was delivered"
    carried: dict[tuple[int, int], set] = {}
    for _, a, b, cells in s.journal.deliveries:
        got = carried.setdefault((a, b), set())
        assert not got & set(cells.tolist()), f"a cell went twice from {a} to {b}"
        got |= set(cells.tolist())
    # nothing is sent back the way it came: a cell b received from a, b never sends to a
    for (a, b), cells in carried.items():
        assert not cells & carried.get((b, a), set()) or link.get("latency", 0) > 0 or \
            _first_from(s.journal.deliveries, a, b, cells & carried[(b, a)])
    # every byte of the ledger is a peer message, charged to its sender
    assert run.ledger and all(m.direction == PEER for m in run.ledger)
    assert run.summary.bytes_up + run.summary.bytes_down == sum(m.bytes for m in run.ledger)


def _first_from(deliveries, a, b, cells) -> bool:
    """Both ways only when the two ends sent a cell in the same round (neither held the other's yet)."""
    first = {}
    for rnd, x, y, cs in deliveries:
        for c in cs.tolist():
            if c in cells:
                first.setdefault((x, y, c), rnd)
    return all(first[(a, b, c)] == first[(b, a, c)] for c in cells)


def test_raw_gossip_on_a_perfect_complete_mesh_gives_everyone_every_observation():
    truth = maze(32, seed=5)
    cfg = _mission(link=dict(topology="mesh", loss=0.0), strategies=("raw",), steps=40)
    res = run_mission(cfg, truth)
    s = res.runs["raw"].sharing
    last = cfg.sync_steps[-1]
    union = np.full(truth.shape, UNKNOWN, dtype=np.uint8)
    for r in s.team:
        seen = (r.obs_step >= 0) & (r.obs_step <= last)
        union[seen] = r.local[seen]
    for k in range(cfg.rovers):
        b = s.belief(k)
        assert ((b == union) | (union == UNKNOWN)).all() and (b[union != UNKNOWN] == union[union != UNKNOWN]).all()
    assert (s.global_map()[union != UNKNOWN] == union[union != UNKNOWN]).all()


def test_a_leader_keeps_the_team_sharing_while_the_lander_is_cut():
    truth = maze(40, seed=1)
    link = dict(loss=0.0, lander_cut=(10, 60), peer_range=30.0)
    star = run_mission(_mission(link=dict(link, topology="star"), strategies=("raw",)), truth).runs["raw"]
    lead = run_mission(_mission(link=dict(link, topology="leader"), strategies=("raw",)), truth).runs["raw"]
    in_cut = [m for m in star.ledger if 10 <= m.step < 60]
    assert in_cut and all(m.status == "link down" for m in in_cut)
    # during the cut the lander is in no group: every message is between rovers
    lead_cut = [m for m in lead.ledger if 10 <= m.step < 60]
    assert lead_cut and all(BASE not in (m.rover, m.to) for m in lead_cut)
    assert any(m.status == "delivered" for m in lead_cut)


def test_the_same_seed_gives_the_same_mesh_mission():
    truth = maze(32, seed=3)
    cfg = _mission(link=dict(topology="mesh", loss=0.3, drop=0.5), strategies=("raw",))
    a, b = (run_mission(cfg, truth).runs["raw"] for _ in range(2))
    assert [m.to_dict() for m in a.ledger] == [m.to_dict() for m in b.ledger]
    assert a.series.accuracy == b.series.accuracy


def test_model_gossip_shares_and_improves_beliefs_over_none():
    truth = maze(32, seed=4)
    cfg = _mission(link=dict(topology="mesh", loss=0.0), strategies=("none", "gossip"), steps=30,
                   methods={"gossip": {"epochs": 20}})
    res = run_mission(cfg, truth)
    g = res.runs["gossip"]
    assert any(m.status == "delivered" and m.kind == "model" for m in g.ledger)
    assert g.sharing.journal.rejected == 0
    assert np.mean(g.series.accuracy[-1]) > np.mean(res.runs["none"].series.accuracy[-1])


def test_strategies_that_need_a_base_are_refused_on_a_mesh():
    with pytest.raises(FedmapError, match="needs the star topology"):
        MissionConfig(strategies=("raw", "predictive"), link=LinkConfig(topology="mesh"))
    with pytest.raises(FedmapError, match="did you mean 'mesh'"):
        LinkConfig(topology="mseh")
    assert MissionConfig(link=LinkConfig(topology="leader")).strategies == ("none", "raw", "gossip", "central")


# -- helicopters --------------------------------------------------------------------------------

def test_block_classes_and_coarse_footprint_by_brute_force():
    rng = np.random.default_rng(0)
    c = rng.choice([FREE, IMPASSABLE], size=(13, 10), p=[0.9, 0.1]).astype(np.uint8)
    c[:4, :4] = FREE
    for f in (1, 2, 3, 4):
        blocks = block_classes(c, f, UNKNOWN)
        for i in range(blocks.shape[0]):
            for j in range(blocks.shape[1]):
                cells = set(c[i * f:(i + 1) * f, j * f:(j + 1) * f].ravel().tolist())
                assert blocks[i, j] == (cells.pop() if len(cells) == 1 else UNKNOWN)
        m = coarse_footprint((5, 4), c.shape, 4.5, f)
        for r in range(13):
            for q in range(10):
                centre = ((r // f) * f + (f - 1) / 2, (q // f) * f + (f - 1) / 2)
                assert m[r, q] == (np.hypot(centre[0] - 5, centre[1] - 4) <= 4.5)


@pytest.mark.parametrize("budget,recharge,speed", [(6, 3, 3), (10, 1, 5), (4, 7, 2)])
def test_a_helicopter_keeps_its_flight_budget_and_lands_on_landing_sites(budget, recharge, speed):
    truth = maze(48, seed=6)
    heli = HelicopterConfig(speed=speed, sensor_radius=6.0, resolution=2, flight_budget=budget, recharge=recharge)
    cfg = _mission(helicopters=1, helicopter=heli, steps=80)
    res = run_mission(cfg, truth)
    for name, run in res.runs.items():
        h = run.sharing.team[cfg.rovers]
        assert h.kind == "helicopter" and h.landings, f"{name}: the helicopter never landed"
        # from the step log: no stretch in the air is longer than the budget, and each ends on a site
        runs, n = [], 0
        for flew in h.airborne:
            if flew:
                n += 1
            elif n:
                runs.append(n)
                n = 0
        assert len(h.airborne) == cfg.steps
        assert max(runs + [n]) <= budget
        assert len(runs) == len(h.landings)
        for (step, cell, flown, site), stretch in zip(h.landings, runs):
            assert flown == stretch
            assert recharge == 0 or step >= cfg.steps or not h.airborne[step]  # down the step after landing
            assert cell == res.base or (truth.classes[cell] == FREE and h.local[cell] == FREE)
            assert site == ("lander" if cell == res.base else "observed free")
            assert all(not f for f in h.airborne[step:step + recharge])  # recharging
        # what it saw is the truth, at coarse resolution: uniform blocks only
        seen = h.local != UNKNOWN
        assert (h.local[seen] == truth.classes[seen]).all()
        blocks = block_classes(truth.classes, heli.resolution, UNKNOWN)
        rr, cc = np.nonzero(seen)
        assert (blocks[rr // heli.resolution, cc // heli.resolution] != UNKNOWN).all()


def test_admm_consensus_step_is_the_minimiser():
    from scipy.optimize import minimize

    from fedmap.federation.aggregate import admm_consensus
    rng = np.random.default_rng(1)
    for rho in (1e-3, 0.1, 2.0):
        p = rng.normal(size=4)
        mids = [rng.normal(size=4) for _ in range(int(rng.integers(1, 4)))]

        def objective(t, p=p, mids=mids, rho=rho):
            return float(t @ p + rho * sum(((t - m) ** 2).sum() for m in mids))

        ref = minimize(objective, np.zeros(4), method="BFGS", options={"gtol": 1e-10}).x
        np.testing.assert_allclose(admm_consensus(p, mids, rho), ref, rtol=1e-4, atol=1e-4)


def test_admm_runs_on_a_mesh_and_keeps_duals_per_link():
    truth = maze(32, seed=4)
    cfg = _mission(link=dict(topology="mesh", loss=0.0), strategies=("none", "admm"), steps=20,
                   methods={"admm": {"epochs": 10}})
    res = run_mission(cfg, truth)
    s = res.runs["admm"].sharing
    # a complete mesh of the lander and 3 rovers: every agent holds a dual per neighbour
    assert {a: sorted(p.dual) for a, p in s.peers.items()} == {a: [j for j in (BASE, 0, 1, 2) if j != a]
                                                             for a in (BASE, 0, 1, 2)}
    # the shared model tells every rover cells it never observed, rightly (none's beliefs know only their own)
    for k, r in enumerate(s.team):
        told = (s.belief(k) == truth.classes) & (r.local == UNKNOWN)
        assert told.sum() > 0.05 * truth.classes.size
    none = res.runs["none"].sharing
    assert all(((none.belief(k) != UNKNOWN) == (r.local != UNKNOWN)).all() for k, r in enumerate(none.team))


# -- per-rover traversability profiles -------------------------------------------------------

def test_each_rover_plans_on_its_own_profile_and_is_scored_on_it():
    from fedmap.evaluation.paths import path_f1
    from fedmap.mission import load_mission, mission_terrain

    cfg, source, _ = load_mission(mission={"rovers": 3, "steps": 60, "sync_every": 10, "eval_pairs": 10,
                                           "profiles": "cadre,team,msl", "strategies": "raw"},
                                  terrain={"kind": "builtin", "terrain": "mars"}, size=64)
    assert cfg.profiles == ("cadre", "team", "msl")
    truth, elevation, prior, profiles = mission_terrain(cfg, source)
    assert sorted(profiles) == ["cadre", "msl"]
    # the rovers' limits (cadre 20 deg, msl 30 deg) are looser than the shared 15 deg: each sees more free ground
    for name in ("cadre", "msl"):
        assert (profiles[name] == FREE).sum() > (truth.classes == FREE).sum()
    res = run_mission(cfg, truth, elevation=elevation, prior=prior, profiles=profiles)
    run = res.runs["raw"]
    s = run.sharing
    own = [profiles["cadre"], truth.classes, profiles["msl"]]
    for k, r in enumerate(s.team):
        assert all(own[k][c] == FREE for c in r.trail), f"rover {k} entered a cell its own profile forbids"
        # its belief F1 is scored against the truth under its own profile, on its own view
        view = s.belief(k) if r.own is None else np.where(r.own != UNKNOWN, r.own, s.belief(k))
        want = path_f1(own[k], view, n_pairs=cfg.eval_pairs, seed=cfg.seed).f1
        assert run.series.eval.belief_f1[-1][k] == pytest.approx(want)
    # the msl rover drives where the shared map says impassable: its own limits allow it
    msl = s.team[2]
    assert any(truth.classes[c] == IMPASSABLE for c in msl.trail)
    # shared classes follow [thresholds]: what the base holds is the shared truth's
    g = s.global_map()
    assert (g[g != UNKNOWN] == truth.classes[g != UNKNOWN]).all()


def test_profiles_are_checked():
    with pytest.raises(FedmapError, match="did you mean 'cadre'"):
        MissionConfig(rovers=2, profiles=("cadre", "cadr"))
    with pytest.raises(FedmapError, match="2 profiles for 3 rovers"):
        MissionConfig(rovers=3, profiles=("cadre", "msl"))
    assert MissionConfig(rovers=3, profiles=("msl",)).rover_profiles == ("msl", "msl", "msl")  # one for all
    with pytest.raises(FedmapError, match="no classes given"):
        run_mission(MissionConfig(rovers=1, steps=2, profiles=("msl",), strategies=("none",)), maze(16))


# -- the elevation layer in a mission ------------------------------------------------------------

def _elevation_mission(noise: float, q: float, strategies=("raw",)):
    from fedmap.mission import load_mission, mission_terrain

    cfg, source, _ = load_mission(mission={"rovers": 3, "steps": 40, "sync_every": 10, "eval_pairs": 10,
                                           "profiles": "cadre,team,msl", "strategies": ",".join(strategies),
                                           "layers": "classes,elevation", "elevation_noise_m": noise,
                                           "elevation_q_m": q},
                                  terrain={"kind": "builtin", "terrain": "moon"}, size=64)
    truth, elevation, prior, profiles = mission_terrain(cfg, source)
    res = run_mission(cfg, truth, elevation=elevation, prior=prior, profiles=profiles,
                      thresholds=source.thresholds)
    return cfg, truth, elevation, profiles, res


def test_shared_exact_heights_let_each_rover_derive_its_own_classes():
    from scipy import ndimage

    cfg, truth, elevation, profiles, res = _elevation_mission(noise=0.0, q=0.0)
    s = res.runs["raw"].sharing
    for r in s.team:
        seen = np.isfinite(r.heights)
        assert np.array_equal(r.heights[seen], elevation[seen])  # exact sensing
        assert (seen == (r.local != UNKNOWN)).all()
    z = s.global_heights()
    held = np.isfinite(z)
    assert held.any() and np.array_equal(z[held], elevation[held])  # exact sharing (q = 0)
    assert res.runs["raw"].summary.final_height_rmse_m == 0.0
    own = [profiles["cadre"], truth.classes, profiles["msl"]]
    for k in range(cfg.rovers):
        # where every cell within 2 of a cell has a height, the classes it derives are its profile's truth
        r = s.team[k]
        zk = np.where(np.isfinite(r.heights), r.heights, s.rovers[k].heights())
        inner = ndimage.binary_erosion(np.isfinite(zk), np.ones((5, 5)), border_value=0)
        received = inner & (r.local == UNKNOWN)
        assert received.any(), f"rover {k} received no heights to derive from"
        view = _run_view(res, "raw", k)
        assert np.array_equal(view[received], own[k][received])


def _run_view(res, name, k):
    """The rover's own view rebuilt from scratch: derived classes over shared heights (for a
    ``team`` rover only where its belief holds no class), own cells on top."""
    from fedmap.maps.dem import Dem
    from fedmap.maps.traversability import dem_to_traversability, rover_profile

    s = res.runs[name].sharing
    r = s.team[k]
    profile = res.config.rover_profiles[k]
    z = np.where(np.isfinite(r.heights), r.heights, s.rovers[k].heights())
    derived = dem_to_traversability(Dem(z, res.truth.pixel_size), None if profile == "team" else
                                    rover_profile(profile)).classes
    belief = s.belief(k)
    use = (derived != UNKNOWN) & ((belief == UNKNOWN) if profile == "team" else True)
    return np.where(use, derived, belief)


def test_height_noise_is_seeded_and_measured():
    _, _, elevation, _, a = _elevation_mission(noise=0.2, q=0.01)
    _, _, _, _, b = _elevation_mission(noise=0.2, q=0.01)
    ra, rb = a.runs["raw"].sharing.team[0], b.runs["raw"].sharing.team[0]
    assert np.array_equal(ra.heights, rb.heights, equal_nan=True)  # the same seed, the same noise
    seen = np.isfinite(ra.heights)
    err = ra.heights[seen] - elevation[seen]
    assert 0.15 < float(np.std(err)) < 0.25 and abs(float(np.mean(err))) < 0.05
    # what the base holds is what the rovers measured, quantised to 1 cm
    z = a.runs["raw"].sharing.global_heights()
    assert 0.15 < a.runs["raw"].summary.final_height_rmse_m < 0.25
    assert np.isfinite(z).sum() > 0


def test_under_leaders_each_admm_agent_takes_one_primal_step_per_round():
    from fedmap.mission.ends.gossip import AdmmPeer

    calls: list[tuple[int, int]] = []
    original = AdmmPeer._primal

    def counting(self, round_no, p_sum, mids):
        calls.append((round_no, self.agent))
        return original(self, round_no, p_sum, mids)

    truth = maze(32, seed=4)
    cfg = _mission(link=dict(topology="leader", loss=0.0, peer_range=100.0), strategies=("admm",), steps=20,
                   methods={"admm": {"epochs": 3}})
    AdmmPeer._primal = counting
    try:
        run_mission(cfg, truth)
    finally:
        AdmmPeer._primal = original
    assert calls and len(calls) == len(set(calls))  # never twice in one round
    assert {r for r, _ in calls} == set(range(1, len(cfg.sync_steps) + 1))
    assert {i for _, i in calls} == {0, 1, 2}  # the lander (the leader) takes the exact step instead
