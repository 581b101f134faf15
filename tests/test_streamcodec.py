"""The predictive coder (fedmap.coding.streamcodec), its learned prior, and the
``predictive`` mission strategy against ``raw``."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from conftest import maze
from fedmap.coding import streamcodec as sc
from fedmap.errors import FedmapError, RejectedUpdate
from fedmap.maps.grid import FREE, IMPASSABLE, UNKNOWN, GridMap
from fedmap.meta.collections import MapCollection
from fedmap.mission import LinkConfig, MissionConfig, run_mission
from fedmap.mission.ends.protocol import cover
from fedmap.training.coderprior import _scaled, learn_coder_prior, save_coder_prior

SHAPE = (40, 48)


def _terrain(seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    m = np.zeros(SHAPE, dtype=np.uint8)
    for _ in range(10):
        r, c = rng.integers(0, SHAPE[0] - 5), rng.integers(0, SHAPE[1] - 5)
        m[r:r + rng.integers(1, 6), c:c + rng.integers(1, 6)] = IMPASSABLE
    return m


def _walk(start, n, seed):
    rng = np.random.default_rng(seed)
    out, p = [], start
    for _ in range(n):
        while True:
            dr, dc = sc.MOVES[rng.integers(8)]
            q = (p[0] + dr, p[1] + dc)
            if 0 <= q[0] < SHAPE[0] and 0 <= q[1] < SHAPE[1]:
                break
        out.append(q)
        p = q
    return out


def _message(seed: int = 0, known_from=None):
    """A rover-like message: a walk, the cells in range of it that the receiver lacks."""
    truth = _terrain(seed)
    anchor = (20, 24)
    track = _walk(anchor, 15, seed)
    known = np.full(SHAPE, UNKNOWN, np.uint8) if known_from is None else known_from
    derive = lambda tracks: cover([anchor, *tracks[0]], SHAPE, 5.0)  # noqa: E731
    cand = derive([track]) & (known == UNKNOWN)
    cells = np.where(cand, truth, UNKNOWN).astype(np.uint8)
    content = sc.Content([track], [(3, 4), None], cells)
    return content, dict(anchors=[anchor], mark_refs=[None, (1, 1)], known=known, candidates=derive)


def test_a_message_round_trips_and_both_ends_learn_the_same_counts():
    content, kw = _message()
    state = sc.blank_state()
    payload, fold = sc.encode(content, state=state, **kw)
    got = sc.decode(payload, state=state.copy(), **kw)
    assert got.tracks == content.tracks and got.marks == content.marks
    np.testing.assert_array_equal(got.cells, content.cells)
    for name in ("cells", "moves", "lengths", "marks"):
        np.testing.assert_array_equal(getattr(got.fold, name), getattr(fold, name))
    # the fold counts every coded symbol once: the candidate cells, the moves, the marks
    n_cand = int((kw["candidates"]([content.tracks[0]]) & (kw["known"] == UNKNOWN)).sum())
    assert fold.cells.sum() == n_cand and fold.moves.sum() == 15 and fold.marks.sum() == 2
    # the cells' counts by class are the message's classes, counted by hand
    by_class = fold.cells.sum(axis=(0, 1))
    assert by_class[FREE] == (content.cells == FREE).sum() and by_class[IMPASSABLE] == (content.cells == 1).sum()


def test_the_persistent_state_makes_the_next_message_cheaper():
    content, kw = _message(seed=1)
    state = sc.blank_state()
    first, fold = sc.encode(content, state=state, **kw)
    state.fold(fold)
    again, _ = sc.encode(content, state=state, **kw)
    assert len(again) < len(first)
    # and it decodes only with the state it was coded with
    with pytest.raises(RejectedUpdate, match="coder state"):
        sc.decode(again, state=sc.blank_state(), **kw)
    assert sc.decode(again, state=state, **kw).tracks == content.tracks


def test_the_code_length_is_close_to_the_ideal_of_its_own_probabilities():
    # an independent reference: a message of cells only, all FREE with a known state, must
    # cost about sum(-log2 p) of the model's probabilities (computed here from the counts)
    state = sc.blank_state()
    state.cells[..., FREE] = 1000
    state.cells[..., IMPASSABLE] = 10
    state.cells[..., UNKNOWN] = 10
    known = np.full(SHAPE, UNKNOWN, np.uint8)
    cells = np.zeros(SHAPE, np.uint8)
    derive = lambda tracks: np.ones(SHAPE, bool)  # noqa: E731
    payload, _ = sc.encode(sc.Content([], [], cells), state=state, anchors=[], mark_refs=[], known=known,
                           candidates=derive)
    p_free = (1000 + sc.ALPHA) / (1020 + 3 * sc.ALPHA)  # every context; counts only grow toward FREE
    upper_bits = cells.size * -math.log2(p_free) + 2 * 8 + 32 + 16  # framing, a final word, the flags
    assert 8 * len(payload) <= upper_bits


def test_cells_outside_the_candidates_and_bad_input():
    content, kw = _message(seed=2)
    extra = content.cells.copy()
    extra[0, 0] = IMPASSABLE  # far from the track: not a candidate
    msg = sc.Content(content.tracks, content.marks, extra)
    payload, _ = sc.encode(msg, state=sc.blank_state(), **kw)
    np.testing.assert_array_equal(sc.decode(payload, state=sc.blank_state(), **kw).cells, extra)
    with pytest.raises(FedmapError, match="neighbouring cells"):
        sc.encode(sc.Content([[(30, 30)]], content.marks, content.cells), state=sc.blank_state(), **kw)
    known = kw["known"].copy()
    known[content.cells != UNKNOWN] = FREE
    with pytest.raises(FedmapError, match="already holds"):
        sc.encode(content, state=sc.blank_state(), **{**kw, "known": known})


def test_a_receiver_holding_another_map_rejects_the_message():
    content, kw = _message(seed=3)
    payload, _ = sc.encode(content, state=sc.blank_state(), **kw)
    other = kw["known"].copy()
    other[20:23, 24:27] = IMPASSABLE  # the receiver holds cells the sender did not count on
    with pytest.raises(RejectedUpdate):
        sc.decode(payload, state=sc.blank_state(), **{**kw, "known": other})


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.binary(max_size=200))
def test_random_bytes_get_a_clean_rejection(data):
    _, kw = _message(seed=4)
    try:
        got = sc.decode(data, state=sc.blank_state(), **kw)
    except RejectedUpdate as e:
        assert "\n" not in str(e)
    else:  # a lucky payload decodes to something well formed
        assert got.cells.shape == SHAPE and all(0 <= p[0] < SHAPE[0] for t in got.tracks for p in t)


@settings(max_examples=300, deadline=None)
@given(st.data())
def test_mutated_payloads_get_a_clean_rejection(data):
    content, kw = _message(seed=5)
    payload = bytearray(sc.encode(content, state=sc.blank_state(), **kw)[0])
    i = data.draw(st.integers(0, len(payload) - 1))
    payload[i] ^= data.draw(st.integers(1, 255))
    cut = data.draw(st.integers(1, len(payload)))
    try:
        sc.decode(bytes(payload[:cut]), state=sc.blank_state(), **kw)
    except RejectedUpdate as e:
        assert "\n" not in str(e)


def test_scaling_a_prior_keeps_proportions_and_every_seen_class():
    a = np.array([[600, 300, 1], [2, 1, 0], [0, 0, 0]])
    got = _scaled(a, 60)
    np.testing.assert_array_equal(got, [[40, 20, 1], [2, 1, 0], [0, 0, 0]])  # 600 * 60/901 = 39.96 -> 40


def test_a_prior_learned_on_open_ground_predicts_free(tmp_path):
    open_ground = [GridMap(np.zeros((48, 48), np.uint8), 1.0, f"open {i}") for i in range(2)]
    state = learn_coder_prior(MapCollection("open", {"open": open_ground}), steps=20, rovers=2, total=50)
    by_class = state.cells.sum(axis=(0, 1))
    assert by_class[FREE] > 10 * max(by_class[IMPASSABLE], 1)
    assert state.cells.sum(axis=-1).max() <= 50 + 3
    path = save_coder_prior(state, tmp_path / "prior.npz")
    with np.load(path) as z:
        np.testing.assert_array_equal(z["cells"], state.cells)


# ---------------------------------------------------------------- the mission strategy

def _maze(seed: int = 3) -> GridMap:
    return maze(48, seed, blocks=14)


@pytest.mark.parametrize("link", [
    LinkConfig(loss=0.3, seed=1),
    LinkConfig(loss=0.2, latency=3, seed=2),
    LinkConfig(loss=0.1, latency=7, seed=3),  # longer than a sync: messages overlap in flight
])
def test_predictive_reaches_raws_map_for_fewer_bytes_and_both_ends_stay_identical(link):
    config = MissionConfig(rovers=3, steps=60, sync_every=5, sensor_radius=4.0, strategies=("raw", "predictive"),
                           eval_pairs=5, link=link)
    result = run_mission(config, _maze(), frames=1)
    raw, pred = result.runs["raw"], result.runs["predictive"]
    s = pred.sharing
    for k in range(config.rovers):
        rover, base = s.rovers[k], s.base
        assert rover.up.same_as(base.up[k]) and rover.down.same_as(base.down[k])
        # what the base believes a rover holds is what it holds
        np.testing.assert_array_equal(base.held_by[k], rover.held())
        # every cell a rover holds from the base is true
        held = rover.held() != UNKNOWN
        np.testing.assert_array_equal(rover.held()[held], result.truth.classes[held])
    # the base holds exactly the delivered observations: the union of what each rover delivered
    union = np.full(result.truth.shape, UNKNOWN, np.uint8)
    for k, r in enumerate(s.team):
        union = np.where(s.rovers[k].delivered_cells, r.local, union)
    np.testing.assert_array_equal(s.global_map(), union)
    bytes_raw = sum(m.bytes for m in raw.ledger)
    bytes_pred = sum(m.bytes for m in pred.ledger)
    assert bytes_pred < bytes_raw


def test_without_loss_predictive_ends_with_raws_maps():
    config = MissionConfig(rovers=3, steps=50, sync_every=5, sensor_radius=4.0, strategies=("raw", "predictive"),
                           eval_pairs=5, link=LinkConfig(loss=0.0))
    result = run_mission(config, _maze(seed=5), frames=1)
    a, b = result.runs["raw"].sharing, result.runs["predictive"].sharing
    np.testing.assert_array_equal(a.global_map(), b.global_map())
    for k in range(config.rovers):
        np.testing.assert_array_equal(a.belief(k), b.belief(k))


def test_predictive_fits_a_tight_budget_by_sending_a_prefix_of_the_trail():
    config = MissionConfig(rovers=2, steps=60, sync_every=10, sensor_radius=4.0, strategies=("predictive",),
                           eval_pairs=5, link=LinkConfig(loss=0.0, uplink_bytes=6, downlink_bytes=8))
    run = run_mission(config, _maze(seed=6), frames=1).runs["predictive"]
    sent = [m for m in run.ledger if m.bytes]
    assert sent and all(m.bytes <= (6 if m.direction == "up" else 8) for m in sent)
    s = run.sharing
    for k in range(2):  # the base holds a prefix of each trail, and the cells in range of it
        assert s.base.trails[k] == s.team[k].trail[:len(s.base.trails[k])]
        assert len(s.base.trails[k]) < len(s.team[k].trail)
    again = run_mission(replace(config, link=replace(config.link, uplink_bytes=None, downlink_bytes=None)),
                        _maze(seed=6), frames=1).runs["predictive"]
    assert sum(m.bytes for m in again.ledger) > sum(m.bytes for m in run.ledger)


def test_an_observer_sees_every_cell_both_ends_code_and_nothing_changes():
    """``observe_cells`` tells an observer of every cell coded: the encoder's and the
    decoder's symbols are the message's cells in the same order (counted against the fold,
    which the coder keeps itself), their bits are the ideal code length of the probabilities
    they were coded with (recomputed here), and the payload is the one coded unobserved."""
    content, kw = _message()
    plain, _ = sc.encode(content, state=sc.blank_state(), **kw)
    seen: list = []
    with sc.observe_cells(seen.append):
        payload, fold = sc.encode(content, state=sc.blank_state(), **kw)
        sc.decode(payload, state=sc.blank_state(), **kw)
    assert payload == plain
    enc = [c for c in seen if c.encoding]
    dec = [c for c in seen if not c.encoding]
    assert enc and len(enc) == len(dec) and all(c.anchors == 1 for c in seen)
    for a, b in zip(enc, dec):
        np.testing.assert_array_equal(a.symbols, b.symbols)
        np.testing.assert_allclose(a.probs, b.probs)
    symbols = np.concatenate([c.symbols for c in enc])
    assert np.bincount(symbols, minlength=3).tolist() == fold.cells.sum(axis=(0, 1)).tolist()
    bits = sum(float(-np.log2(c.probs[np.arange(c.symbols.size), c.symbols]).sum()) for c in enc)
    assert bits == pytest.approx(sum(c.bits() for c in enc)) and bits <= 8 * len(payload)
    with sc.observe_cells(seen.append):
        pass
    n = len(seen)
    sc.encode(content, state=sc.blank_state(), **kw)  # no observer left behind
    assert len(seen) == n
