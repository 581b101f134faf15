"""The predictive coder with the map predictor's guess as a context (issue 35, coding):
``[strategies.predictive] predictor = "mix"`` or ``"bins"``."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import maze
from fedmap.coding import streamcodec as sc
from fedmap.errors import FedmapError, RejectedUpdate
from fedmap.maps.grid import IMPASSABLE, UNKNOWN
from fedmap.mission import LinkConfig, MissionConfig, run_mission
from fedmap.mission.ends.predictive import PredictiveOptions
from fedmap.mission.ends.protocol import cover
from fedmap.nets.predictor import predict, shipped_predictor

N = 48
MODES = ("mix", "bins")


def _truth(seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    m = np.zeros((N, N), dtype=np.uint8)
    for _ in range(14):
        r, c = rng.integers(0, N - 8, size=2)
        m[r:r + rng.integers(2, 9), c:c + rng.integers(2, 9)] = IMPASSABLE
    return m


def _messages(seed: int = 0, n: int = 4):
    """A rover's first ``n`` messages: a walk in legs, each leg's new cells in range of it;
    yields ``(content, kwargs)`` with the receiver's map before the message as ``known``."""
    truth = _truth(seed)
    rng = np.random.default_rng(seed + 100)
    known = np.full((N, N), UNKNOWN, np.uint8)
    known[18:30, 2:14] = truth[18:30, 2:14]  # what the receiver holds from before
    pos = (24, 8)
    for i in range(n):
        a, track = pos, []  # a leg starts where the last one ended (its anchor)
        drift = ((-1, 1), (0, 1), (1, 1), (0, 1))[i % 4]  # legs go east, with jitter
        for _ in range(10):
            while True:
                dr, dc = drift if rng.random() < 0.6 else sc.MOVES[rng.integers(8)]
                q = (pos[0] + dr, pos[1] + dc)
                if 3 <= q[0] < N - 3 and 3 <= q[1] < N - 3:
                    break
            track.append(q)
            pos = q
        derive = lambda tracks, a=a: cover([a, *tracks[0]], (N, N), 5.0)  # noqa: E731
        cells = np.where(derive([track]) & (known == UNKNOWN), truth, UNKNOWN).astype(np.uint8)
        yield sc.Content([track], [track[-1]], cells), dict(anchors=[a], mark_refs=[None], known=known.copy(),
                                                           candidates=derive)
        known = np.where(cells != UNKNOWN, cells, known).astype(np.uint8)


def _guess(known: np.ndarray) -> np.ndarray:
    return predict(shipped_predictor(), known)[1]


@pytest.mark.parametrize("mode", MODES)
def test_messages_with_the_guess_round_trip_between_separate_ends(mode):
    sender = sc.guessing_state(sc.initial_state(), mode)
    receiver = sc.guessing_state(sc.initial_state(), mode)
    assert (sender.binned is not None) == (mode == "bins")
    for content, kw in _messages(seed=1):
        # each end computes the guess on its own copy of the map the receiver holds
        payload, fold = sc.encode(content, state=sender, guess=_guess(kw["known"].copy()), **kw)
        got = sc.decode(bytes(payload), state=receiver, guess=_guess(kw["known"].copy()), **kw)
        np.testing.assert_array_equal(got.cells, content.cells)
        assert got.tracks == content.tracks and got.marks == content.marks
        assert (content.cells != UNKNOWN).sum() > 20
        sender.fold(fold)
        receiver.fold(got.fold)
        assert sender.same_as(receiver)
    assert sender.seq == 4


@pytest.mark.parametrize("mode", MODES)
def test_a_receiver_with_another_guess_does_not_get_the_senders_cells(mode):
    """The guess is part of the model: decoding with a guess made on another map (or without
    one) never returns the sender's cells silently."""
    content, kw = next(_messages(seed=2))
    state = sc.guessing_state(sc.initial_state(), mode)
    right = _guess(kw["known"])
    other_map = kw["known"].copy()
    other_map[:, :8] = IMPASSABLE  # the receiver's predictor ran on another map
    wrong = _guess(other_map)
    assert not np.array_equal(right, wrong)
    payload, _ = sc.encode(content, state=state, guess=right, **kw)
    assert sc.encode(content, state=state, guess=wrong, **kw)[0] != payload  # the guess changes the bytes
    for bad in (wrong, 1.0 - right):
        try:
            got = sc.decode(payload, state=state.copy(), guess=bad, **kw)
        except RejectedUpdate:
            continue
        assert not np.array_equal(got.cells, content.cells)
    if mode == "bins":
        with pytest.raises(RejectedUpdate, match="guess"):
            sc.decode(payload, state=state.copy(), **kw)
    else:
        try:
            got = sc.decode(payload, state=state.copy(), **kw)
        except RejectedUpdate:
            pass
        else:
            assert not np.array_equal(got.cells, content.cells)


def test_mixing_by_hand_and_a_guess_that_agrees_costs_fewer_bits():
    p = np.array([[0.5, 0.3, 0.2], [0.1, 0.1, 0.8]])
    out = sc._mixed(p, np.array([0.9, 0.5]), 1 + sc.LEVELS - 1)  # a table at level s >= 4
    a, b, c = sc.MIX[-1]
    z = a * np.log(0.3 / 0.5) + b * np.log(9.0) + c
    np.testing.assert_allclose(out[0, 1], 0.8 / (1 + np.exp(-z)))
    np.testing.assert_allclose(out.sum(axis=1), 1.0)
    np.testing.assert_allclose(out[:, 2], p[:, 2])  # P(not carried) is the count model's
    np.testing.assert_array_equal(sc._mixed(p, np.array([0.9, 0.5]), 1), p)  # s = 1: not mixed
    # a guess that knows the truth shrinks a message; one that contradicts it grows it
    truth = _truth(3)  # one message carrying a whole map
    content = sc.Content([[]], [], truth)
    kw = dict(anchors=[(0, 0)], mark_refs=[], known=np.full((N, N), UNKNOWN, np.uint8),
              candidates=lambda tracks: np.ones((N, N), bool))
    state = sc.guessing_state(sc.initial_state(), "mix")
    truth_guess = np.where(truth == IMPASSABLE, 0.99, 0.01)
    plain = len(sc.encode(content, state=sc.initial_state(), **kw)[0])
    assert len(sc.encode(content, state=state, guess=truth_guess, **kw)[0]) < plain
    assert len(sc.encode(content, state=state, guess=1.0 - truth_guess, **kw)[0]) > plain


def test_bad_guesses_and_options_are_one_line_errors():
    content, kw = next(_messages())
    with pytest.raises(FedmapError, match="guess of shape"):
        sc.encode(content, state=sc.initial_state(), guess=np.zeros((3, 3)), **kw)
    with pytest.raises(FedmapError, match="mix or bins"):
        sc.guessing_state(sc.initial_state(), "neural")
    with pytest.raises(FedmapError, match="predictor"):
        PredictiveOptions(predictor="learned")
    assert sc.guessing_state(sc.initial_state(), "bins").copy().same_as(sc.guessing_state(sc.initial_state(), "bins"))
    assert not sc.guessing_state(sc.initial_state(), "bins").same_as(sc.initial_state())


@pytest.mark.parametrize("mode", MODES)
def test_a_mission_with_the_guess_delivers_the_same_map_and_both_ends_stay_identical(mode):
    config = MissionConfig(rovers=2, steps=40, sync_every=5, sensor_radius=4.0, strategies=("predictive",),
                           eval_pairs=5, link=LinkConfig(loss=0.2, seed=4))
    plain = run_mission(config, maze(48, 3, blocks=14), frames=1).runs["predictive"]
    with_guess = run_mission(MissionConfig(**{**config.__dict__, "methods": {"predictive": {"predictor": mode}}}),
                             maze(48, 3, blocks=14), frames=1).runs["predictive"]
    a, b = plain.sharing, with_guess.sharing
    np.testing.assert_array_equal(a.global_map(), b.global_map())  # lossless: the same cells arrive
    for k in range(config.rovers):
        assert b.rovers[k].up.same_as(b.base.up[k]) and b.rovers[k].down.same_as(b.base.down[k])
        np.testing.assert_array_equal(b.base.held_by[k], b.rovers[k].held())
    # the guess took part in the coding
    binned = b.base.up[0].binned
    if mode == "bins":  # each guess bin learned its own counts
        assert binned is not None and not np.array_equal(binned, np.repeat(b.base.up[0].cells, sc.N_BINS, axis=1))
    else:
        assert binned is None and [m.bytes for m in plain.ledger] != [m.bytes for m in with_guess.ledger]


def test_guesses_that_differ_in_the_last_float32_bits_still_decode():
    """The coder uses the guess quantised (:data:`streamcodec.GUESS_STEPS`), so a receiver
    whose predictor rounds differently in the last bits still gets the cells."""
    content, kw = next(_messages(seed=4))
    guess = _guess(kw["known"]).astype(np.float32)
    centres = (np.arange(sc.GUESS_STEPS) + 0.5) / sc.GUESS_STEPS
    guess = centres[np.clip((guess * sc.GUESS_STEPS).astype(int), 0, sc.GUESS_STEPS - 1)].astype(np.float32)
    nudged = np.nextafter(guess, np.float32(1.0))  # one float32 step up, never across a step's edge here
    assert not np.array_equal(guess, nudged)
    for mode in MODES:
        state = sc.guessing_state(sc.initial_state(), mode)
        payload, _ = sc.encode(content, state=state, guess=guess, **kw)
        got = sc.decode(payload, state=state.copy(), guess=nudged, **kw)
        np.testing.assert_array_equal(got.cells, content.cells)
    np.testing.assert_array_equal(sc.quantised_guess(guess), sc.quantised_guess(nudged))
    np.testing.assert_allclose(sc.quantised_guess(np.array([0.0, 0.5, 1.0])),
                               np.array([1, sc.GUESS_STEPS + 1, 2 * sc.GUESS_STEPS - 1]) / (2 * sc.GUESS_STEPS))
