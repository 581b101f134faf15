"""Missions whose rovers do not know their poses exactly (``[frames]``,
:class:`~fedmap.mission.settings.FramesConfig`).

**The rover.** Each rover's start pose is off by a seeded draw (an offset and a heading),
and its odometry drifts as it drives: a scale error (wheel slip: the distance it measures
is ``1 + scale`` times the distance it drove) and a heading drift per metre, each drawn
once per rover from the given spreads. The truth keeps the true pose; the rover keeps its
*estimated* pose, a point ``est`` and the heading error ``theta`` of its frame. A cell
``p`` seen from the true cell ``x`` lands, in the rover's frame, at
``est + R(theta) (p - x)``: the rover maps in its own frame, so start errors and drift
misplace its cells. It plans there from its estimated cell; a move it commands to a
neighbouring cell of its frame is driven, on the ground, along the same direction turned
by ``-theta``; its hazard sensing (the cell it is about to enter) is in its body frame, so
a rock misplaced on its map never makes it enter an impassable cell: it marks the cell it
was heading for as impassable and plans again. Its trail (and every safety check) is the
true one.

**The base** (``raw`` and ``predictive`` on the star: :class:`FramedRawBase`,
:class:`~fedmap.mission.ends.framed.FramedPredictiveBase`) keeps each rover's cells in the rover's frame and merges
them into the global map only through a transform it estimated, checked by the
registration gate's test (:func:`~fedmap.maps.registration.agreement`:
the share of shared known cells that agree against chance, Cohen's kappa; :func:`verdict`):

* the global frame is the lander's when the lander imaged the ground around itself at
  landing (``lander_view``: that image is a reference to register on, never merged or
  sent); without it, the first rover whose cells arrive fixes the global frame;
* a rover never placed is registered near its deployment estimate (its frame is the
  lander's within the spreads: headings within 3 spreads + 1 degree, shifts within
  3 spreads + 1 cell; :func:`track`); too little shared to tell, its cells wait for the
  next sync; a kappa below the gate, they are refused and wait too: never merged;
* a placed rover's recent cells (the last ``window`` sync rounds, and every cell still
  waiting) are registered again at every sync near its last transform (headings within
  3 degrees, shifts within 3 cells, wider once its cells have waited ``window`` rounds), on
  the global map without its own cells of those rounds (they sit where its last transform
  put them and would only confirm it): the loop closure that corrects its pose in the
  global frame for the drift. Accepted, the transform moves; too little shared to tell,
  its odometry carries the last transform (``carried``); refused, its cells wait.

Merging lays a rover's cells through the transform with
:func:`~fedmap.maps.registration.combine` (impassable wins: a misplaced free cell never
covers a hazard). Each downlink carries the rover's transform back
(:data:`TRANSFORM_BYTES` bytes, counted): the rover lays the global map into its own frame
with it (:class:`FramedRawRover`, :class:`FramedPredictiveRover`) and reports positions
through it. A downlink leaves out the global cells the rover itself gave: it holds them in
its own frame, where its odometry put them, and they were worse for it laid back through
its transform (docs/frames.md). Until it is placed, a rover plans on its own cells only.

``predictive`` codes an uplink in the rover's frame (its trail as it believes it drove it,
from the cell it was told it starts at, and its cells, against its own cells the base
holds) and a downlink in the global frame (the others' trails as the base placed them by
their transforms, and the global cells the rover lacks, against what it holds).

**Scores** are honest: a rover's belief is put back in the true frame with the transform
the team estimated for it (identity before it is placed, and for ``none``), then the
team's estimate of the global frame (:meth:`FramedRawBase.team_frame`: the lander's image
makes it the identity; without it, the mean of the rovers' placements at their starts),
and compared with the truth; the global map likewise. Coverage counts the cells truly seen.

**On the mesh** (``raw`` gossip, :class:`FramedRawPeer`) there is no base: every agent
places what it receives, and the lander, an agent, holds the global frame.

Runs with ``none``, ``raw`` and ``predictive`` on the star and ``none`` and ``raw`` on the
mesh (with the lander as an agent), in process, rovers only, the team's profile, classes only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fedmap.errors import FedmapError
from fedmap.maps.grid import FREE, IMPASSABLE, UNKNOWN
from fedmap.maps.registration import RigidTransform
from fedmap.mission.ends.framed import SENSED_BEYOND, FramedRawBase, rotation
from fedmap.mission.world.sensing import disk_offsets, footprint
from fedmap.mission.world.world import World

Cell = tuple[int, int]


def check_frames(config: Any, framed: tuple[str, ...] | list[str]) -> None:
    """One-line error when a mission with ``[frames]`` asks for what it does not support
    (``framed``: the strategies that run with it, the registry's)."""
    if not config.frames.enabled:
        return
    bad = [s for s in config.strategies if s not in framed]
    if bad:
        raise FedmapError(f"[frames] (unknown poses, drift) runs {', '.join(framed)} only, not {', '.join(bad)}")
    if config.link.topology not in ("star", "mesh"):
        raise FedmapError(f"[frames] (unknown poses, drift) runs on the star or the mesh, not {config.link.topology!r}")
    if config.link.topology == "mesh" and not config.link.lander_agent:
        raise FedmapError("[frames] on the mesh needs the lander as an agent ([link] lander_agent = true): its frame "
                          "is the global one")
    for asked, what in ((config.helicopters > 0, "helicopters"),
                        (any(p != "team" for p in config.rover_profiles), "rover profiles"),
                        ("elevation" in config.layers, "an elevation layer"),
                        (config.predictor != "none", "a predictor"), (config.mode != "frontier", "waypoints")):
        if asked:
            raise FedmapError(f"[frames] (unknown poses, drift) does not run with {what}")


# --------------------------------------------------------------------------- poses


@dataclass
class Pose:
    """A rover's true cell and its estimate: ``est`` (row, col, floats, in its own frame),
    ``theta`` its frame's heading error (degrees), and its odometry's errors, drawn once:
    ``scale`` (measured distance / driven - 1) and ``rate`` (heading drift, degrees per metre)."""

    true: Cell
    est: np.ndarray
    theta: float
    scale: float
    rate: float
    errors: list = field(default_factory=list)  #: per move: distance (cells) of the estimate from the truth
    cells: list = field(default_factory=list)  #: its estimated cells, in its own frame, as it went (no repeats)

    @classmethod
    def draw(cls, k: int, start: Cell, frames: Any, seed: int) -> Pose:
        rng = np.random.default_rng(np.random.SeedSequence([seed, k, 38]))
        offset = rng.normal(0.0, 1.0, 2) * frames.start_offset
        theta, scale, rate = rng.normal(0.0, 1.0, 3) * (frames.start_heading, frames.drift, frames.heading_drift)
        return cls(start, np.array(start, dtype=np.float64) + offset, float(theta), float(scale), float(rate))

    def cell(self, shape: tuple[int, int]) -> Cell:
        """Its estimated cell (in its own frame, clipped to the grid)."""
        r, c = np.rint(self.est).astype(int)
        return (int(np.clip(r, 0, shape[0] - 1)), int(np.clip(c, 0, shape[1] - 1)))

    def to_own(self) -> RigidTransform:
        """The transform of true cells into its own frame, now: ``p -> est + R(theta) (p - true)``."""
        at = self.est - rotation(self.theta) @ np.array(self.true, dtype=np.float64)
        return RigidTransform(float(at[0]), float(at[1]), self.theta)

    def ground_move(self, d: Cell) -> Cell:
        """The move on the ground of a move ``d`` commanded in its own frame (a neighbour)."""
        g = rotation(-self.theta) @ np.array(d, dtype=np.float64)
        return (int(np.rint(g[0])), int(np.rint(g[1])))

    def moved(self, g: Cell, pixel_size: float) -> None:
        """Dead reckoning after driving ``g`` (a move between neighbouring cells) on the ground."""
        self.est = self.est + (1.0 + self.scale) * (rotation(self.theta) @ np.array(g, dtype=np.float64))
        self.theta += self.rate * math.hypot(*g) * pixel_size
        self.true = (self.true[0] + g[0], self.true[1] + g[1])


class FramedWorld(World):
    """:class:`~fedmap.mission.world.world.World` whose rovers map and plan in their own frames
    (see the module). ``Rover.pos`` is a rover's estimated cell (what it plans from and
    reports), ``Rover.trail`` its true cells; :attr:`poses` holds both."""

    def __init__(self, config, truth, elevation, starts, base, waypoints, **kw) -> None:
        super().__init__(config, truth, elevation, starts, base, waypoints, **kw)
        self.poses = [Pose.draw(k, s, config.frames, config.seed) for k, s in enumerate(starts)]

        self.seen = [np.zeros(truth.shape, dtype=bool) for _ in starts]  # the true cells each has observed
        for r, p in zip(self.team, self.poses):
            r.pos = p.cell(truth.shape)
            p.cells.append(r.pos)
            r.__dict__["frame"] = p  # for the record (benchmarks/mission_frames.py)

    def positions(self) -> list[Cell]:
        """Every rover's true cell (the link's range, the animation)."""
        return [p.true for p in self.poses]

    def observed(self) -> np.ndarray:
        """``(rovers, h, w)``: the true cells each rover has observed."""
        return np.stack(self.seen)

    def in_true_frame(self, k: int, belief: np.ndarray, base: Any = None) -> np.ndarray:
        """Rover ``k``'s belief put back in the true frame by the transforms the team estimated:
        its frame into the global frame (its end's :attr:`FramedRawRover.transform`; identity
        without one), then the global frame into the true one (``base``'s
        :meth:`FramedRawBase.team_frame`; identity without it)."""
        t = getattr(self.ends[k], "transform", RigidTransform())
        if isinstance(base, FramedRawBase) and getattr(self.ends[k], "placed", False):
            t = base.team_frame().compose(t)
        return t.apply(belief, belief.shape)

    def sense(self, k: int, t: int) -> None:
        r, p, c = self.team[k], self.poses[k], self.config
        shape = self.truth.shape
        mask = footprint(p.true, shape, c.sensor_radius, elevation=self.elevation if c.line_of_sight else None,
                         height_m=c.sensor_height_m)
        self.seen[k] |= mask
        # every cell of its own frame within range of its estimate looks up the true cell it shows
        centre = np.rint(p.est).astype(int)
        e = disk_offsets(c.sensor_radius + SENSED_BEYOND) + centre
        e = e[(e[:, 0] >= 0) & (e[:, 0] < shape[0]) & (e[:, 1] >= 0) & (e[:, 1] < shape[1])]
        g = np.rint((e - p.est) @ rotation(-p.theta).T + np.array(p.true)).astype(int)
        ok = (g[:, 0] >= 0) & (g[:, 0] < shape[0]) & (g[:, 1] >= 0) & (g[:, 1] < shape[1])
        e, g = e[ok], g[ok]
        ok = mask[g[:, 0], g[:, 1]] & (r.local[e[:, 0], e[:, 1]] == UNKNOWN)
        e, g = e[ok], g[ok]
        r.local[e[:, 0], e[:, 1]] = self.truth.classes[g[:, 0], g[:, 1]]
        r.obs_step[e[:, 0], e[:, 1]] = t
        r.wrote()
        here = p.cell(shape)  # it stands on free ground, wherever its map put a rock
        if r.local[here] != FREE:
            r.local[here] = FREE
            r.obs_step[here] = t
            r.wrote(here)
        r.pos = here
        if p.cells[-1] != here:
            p.cells.append(here)

    def drive(self, k: int, t: int) -> None:
        r, p = self.team[k], self.poses[k]
        truth = self.truth.classes
        h, w = truth.shape
        for _ in range(self.config.speed):
            belief = self.ends[k].belief()
            self.plan(k, belief)
            if not r.path:
                return
            nxt = r.path[0]
            if belief[nxt] == IMPASSABLE:
                r.replan = True
                return
            g = p.ground_move((nxt[0] - r.pos[0], nxt[1] - r.pos[1]))
            there = (p.true[0] + g[0], p.true[1] + g[1])
            if not (0 <= there[0] < h and 0 <= there[1] < w) or truth[there] == IMPASSABLE:
                # its hazard sensing sees the rock ahead: on its map, where it was heading
                r.local[nxt] = IMPASSABLE
                r.obs_step[nxt] = t
                r.wrote(nxt)
                r.replan = True
                return
            r.path.pop(0)
            r.distance += math.hypot(*g)
            p.moved(g, self.truth.pixel_size)
            r.trail.append(p.true)
            self.sense(k, t)
            p.errors.append(float(np.hypot(*(p.est - np.array(p.true)))))


# --------------------------------------------------------------------------- the transform on the link


__all__ = ["FramedWorld", "Pose", "check_frames"]
