"""A helicopter's flight: its sorties over any terrain, bounded by its flight budget, and
its landings (the lander, or a cell it observed free). :class:`~fedmap.mission.world.world.World`
steps a helicopter with :func:`fly`."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from scipy import ndimage

from fedmap.maps.grid import FREE, UNKNOWN
from fedmap.mission.world.frontiers import choose_target

Cell = tuple[int, int]


def fly(world: Any, k: int, t: int) -> None:
    """One step of helicopter ``k`` of ``world`` (a :class:`~fedmap.mission.world.world.World`):
    see :class:`~fedmap.mission.settings.HelicopterConfig`.

    Its rule keeps ``flight + ceil(d / speed) <= flight_budget`` at every step, ``d``
    the Chebyshev distance to its nearest landing site: a step that would break it is
    flown towards that site instead (8-connected moves shorten it by one cell each), and
    it lands on arriving there. The loop checks the budget and the site and stops with
    an error if the rule ever broke."""
    r, hc = world.team[k], world.config.helicopter
    r.airborne.append(False)
    if r.charging > 0:
        r.charging -= 1
        return
    sites = r.local == FREE
    sites[world.base] = True
    dist = ndimage.distance_transform_cdt(~sites, metric="chessboard")
    budget, speed = hc.flight_budget, hc.speed

    def after(goal: Cell) -> Cell:
        dr, dc = goal[0] - r.pos[0], goal[1] - r.pos[1]
        n = min(speed, max(abs(dr), abs(dc)))
        return (r.pos[0] + int(np.clip(dr, -n, n)), r.pos[1] + int(np.clip(dc, -n, n)))

    def affordable(cell: Cell) -> bool:
        return r.flight + 1 + -(-int(dist[cell]) // speed) <= budget

    if not r.returning:
        belief = world.ends[k].belief()
        if r.target is None or world.target_done(r, belief) or r.pos == r.target:
            flyer = np.where(belief == UNKNOWN, UNKNOWN, FREE).astype(np.uint8)
            reach = dist * 2 <= speed * (budget - 2)
            r.target = choose_target(flyer, r.pos, radius=hc.sensor_radius, unknown_cost=1.0,
                                     others=world.ends[k].others(), allowed=reach)
        if r.target is None or not affordable(after(r.target)):
            r.returning = True
            r.target = None
    if r.returning and dist[r.pos] == 0:  # on a site: land (or stay landed) this step
        if r.flight > 0:
            land(world, k, t)
        r.returning = False
        return
    if r.returning:
        near = np.argwhere(sites)
        d = np.maximum(np.abs(near[:, 0] - r.pos[0]), np.abs(near[:, 1] - r.pos[1]))
        i = int(np.lexsort((near[:, 1], near[:, 0], d))[0])
        goal = (int(near[i, 0]), int(near[i, 1]))
    else:
        assert r.target is not None
        goal = r.target
    for _ in range(speed):
        if r.pos == goal:
            break
        nxt = (r.pos[0] + int(np.sign(goal[0] - r.pos[0])), r.pos[1] + int(np.sign(goal[1] - r.pos[1])))
        r.distance += math.hypot(nxt[0] - r.pos[0], nxt[1] - r.pos[1])
        r.pos = nxt
        r.trail.append(nxt)
        world.sense(k, t)
    r.flight += 1
    r.airborne[-1] = True
    if r.flight > budget:
        raise RuntimeError(f"helicopter {k} flew {r.flight} steps, over its budget of {budget}")
    if r.returning and r.pos == goal:
        land(world, k, t)

def land(world: Any, k: int, t: int) -> None:
    """Helicopter ``k`` lands where it is (the lander, or a cell it observed free) and recharges."""
    r = world.team[k]
    site = "lander" if r.pos == world.base else "observed free"
    if site != "lander" and r.local[r.pos] != FREE:
        raise RuntimeError(f"helicopter {k} landed on {r.pos}, which is not a landing site")
    r.landings.append((t, r.pos, r.flight, site))
    r.flight, r.charging, r.returning = 0, world.config.helicopter.recharge, False


__all__ = ["fly", "land"]
