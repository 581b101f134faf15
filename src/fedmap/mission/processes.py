"""A strategy's ends in OS processes of their own: the base station's end in one, each
rover's end in another, and only bytes between them.

:func:`ends_in_processes` is an ``ends`` factory for :func:`~fedmap.mission.sim.run_mission`.
It starts one process per end (``spawn``: nothing is inherited but what is sent), builds
that end there from the mission's config and truth (:func:`~fedmap.mission.registry.build`,
keeping only its own end), and gives the mission loop a stand-in per end that forwards
each call over a pipe. What goes between two ends is what the topology carries: a payload
(``bytes``), the receiver's one-bit answer, and the acknowledgement. The mission loop is
the rovers' world and the radio: before each call a rover's stand-in sends the rover's own
state (position, target, trail, observations, heights), as its sensors would give it to
its end on the robot, and the scores read each end's belief and the base's global map as
an observer would. The ends of ``none`` and ``central`` use no link and stay in process.
"""

from __future__ import annotations

import multiprocessing as mp
import os
from typing import Any

from fedmap.mission.registry import REGISTRY, Setup, Sharing, build
from fedmap.mission.world import Rover

#: What a rover's end reads of its own rover (sent before every call).
ROVER_STATE = ("pos", "target", "trail", "local", "obs_step", "heights")


def _serve(conn: Any, name: str, config: Any, truth: Any, starts: list, k: int | None, topology: Any) -> None:
    """The process of one end: build it, then answer calls until told to stop."""
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    import numpy as np

    from fedmap.maps.grid import UNKNOWN

    shape = truth.shape
    team = [Rover(tuple(s), np.full(shape, UNKNOWN, np.uint8), np.full(shape, -1, np.int64), trail=[tuple(s)])
            for s in starts]
    sharing = build(name, Setup(config, truth, team, topology))
    end = sharing.base if k is None else sharing.rovers[k]
    while True:
        method, args, state = conn.recv()
        if method is None:
            conn.close()
            return
        if state is not None:
            for field, value in state.items():
                setattr(team[k], field, value)  # type: ignore[index]
        try:
            conn.send(("ok", getattr(end, method)(*args)))
        except Exception as e:  # noqa: BLE001 - handed back to the caller, who raises it
            conn.send(("error", e))


class EndProcess:
    """The mission loop's stand-in for an end in another process: every method call goes
    over the pipe (a rover's stand-in sends its rover's state first)."""

    def __init__(self, process: Any, conn: Any, rover: Rover | None = None) -> None:
        self._process, self._conn, self._rover = process, conn, rover

    def _call(self, method: str, *args: Any) -> Any:
        r = self._rover
        state = None if r is None else {f: getattr(r, f) for f in ROVER_STATE}
        self._conn.send((method, args, state))
        status, value = self._conn.recv()
        if status == "error":
            raise value
        return value

    def __getattr__(self, method: str) -> Any:
        if method.startswith("_"):
            raise AttributeError(method)
        return lambda *args: self._call(method, *args)

    def close(self) -> None:
        """Stop the process (it is joined; a process that does not stop is killed)."""
        try:
            self._conn.send((None, (), None))
        except (BrokenPipeError, OSError):
            pass
        self._process.join(timeout=30)
        if self._process.is_alive():
            self._process.kill()
            self._process.join()


class ProcessSharing(Sharing):
    """A :class:`~fedmap.mission.registry.Sharing` whose ends are :class:`EndProcess`
    stand-ins; :meth:`close` stops them."""

    def close(self) -> None:
        for end in [*self.rovers, *([self.base] if self.base is not None else [])]:
            if isinstance(end, EndProcess):
                end.close()


def ends_in_processes(name: str, setup: Setup) -> Sharing:
    """The ends of a star strategy ``name``, each in a process of its own (an ``ends``
    factory for :func:`~fedmap.mission.sim.run_mission`). Call :meth:`ProcessSharing.close`
    when the run is over (:func:`close_all` does it for a mission's result)."""
    spec = REGISTRY[name]
    if not (spec.on_link and setup.topology.has_base and spec.star is not None):
        return build(name, setup)  # none, central: no link, nothing to separate (peer strategies: not here)
    ctx = mp.get_context("spawn")
    starts = [r.pos for r in setup.team]

    def start(k: int | None) -> EndProcess:
        parent, child = ctx.Pipe()
        p = ctx.Process(target=_serve, args=(child, name, setup.config, setup.truth, starts, k, setup.topology),
                        daemon=True)
        p.start()
        child.close()
        return EndProcess(p, parent, None if k is None else setup.team[k])

    base = start(None)
    rovers = [start(k) for k in range(len(setup.team))]
    # the journals stay with the ends, in their processes: this one records nothing
    return ProcessSharing(name, setup.team, rovers, base)  # type: ignore[arg-type]


def close_all(result: Any) -> None:
    """Stop the processes of every run of a mission result."""
    for run in result.runs.values():
        if isinstance(run.sharing, ProcessSharing):
            run.sharing.close()
