"""A mission as a stream of typed messages: an MCAP recording and a live Foxglove view.

:class:`Recorder` is a ``run_mission(on_snapshot=...)`` callback: it turns every strategy's
:class:`~fedmap.mission.results.Snapshot` into Foxglove messages (``foxglove-sdk``) on the
channels below, written to an MCAP file (:func:`foxglove.open_mcap`) and/or streamed by a
Foxglove WebSocket server (:func:`foxglove.start_server`) while the mission runs.

Channels (``<s>`` is a strategy, ``<k>`` a member of the team: rovers, then helicopters):

| topic | schema | what, when |
|---|---|---|
| ``/tf`` | foxglove.FrameTransforms | ``crs`` -> ``map``, once (live: at each strategy's start) |
| ``/truth`` | foxglove.Grid | the ground truth, once (live: at each strategy's start) |
| ``/<s>/belief/<k>`` | foxglove.Grid | member ``k``'s belief, at the steps it changed |
| ``/<s>/global_map`` | foxglove.Grid | the base's global map, at the steps it changed |
| ``/<s>/scene`` | foxglove.SceneUpdate | members, trails, targets, footprints, the base, links up, leaders; every step |
| ``/<s>/poses`` | foxglove.PosesInFrame | every member's pose (metres, ``map`` frame), every step |
| ``/<s>/link`` | fedmap.LinkMessage (JSON) | one message per ledger entry: its bytes and fate |
| ``/<s>/scores`` | fedmap.StepScores (JSON) | the step's :class:`~fedmap.mission.results.StepRow`, every step |
| ``/<s>/eval`` | fedmap.EvalScores (JSON) | the :class:`~fedmap.mission.results.EvalRow`, at evaluation steps |

**Grids.** Every map is a ``foxglove.Grid`` in the ``map`` frame: a ``classes`` uint8 field
(FREE 0, IMPASSABLE 1, UNKNOWN 2), ``red``/``green``/``blue``/``alpha`` uint8 fields in the
paper's colours (free green, impassable red, unknown grey), and an ``elevation`` float32
field (metres, NaN unknown) where there are heights (the truth's when ``elevation`` is
given, the base's when the mission carries an elevation layer). Foxglove grids run from
their origin along +x (columns, east) and +y (rows, north), so the rows are written bottom
row first.

**Frames.** ``map`` has its origin at the lower-left corner of the map, x east and y north,
in metres (``truth.pixel_size`` per cell): cell ``(row, col)`` is at
``((col + 0.5) * ps, (H - row - 0.5) * ps)``. ``/tf`` places it in ``crs``, the origin of
the truth's CRS: a translation to the map's lower-left corner when the truth has a
transform in a metric CRS (as :func:`fedmap.maps.ros.map_yaml_text` does), else identity
(generated terrain; a geographic CRS, whose degrees are no metres).

**Clock.** One mission step is :data:`STEP_SECONDS` of message time (the mission has no
physical time of its own). In the MCAP every strategy starts at time 0, so the strategies
overlay on one clock and plot side by side. Live, strategies run one after another and a
viewer's clock must not run backwards: strategy ``i`` starts at ``i * (steps + 1)`` steps.

**Cost.** Beliefs and global maps are logged only at the steps they changed (a compare
against the last copy logged); everything else is small. On the default mission
(``fedmap mission``, mars 128², 4 rovers, 150 steps, 5 strategies) the recorder takes about
1.5 ms a snapshot, 1.1 s in all (3-4 % of the mission's 32 s), and writes 2.97 MB (3.9 kB per
strategy and step); docs/robotics.md gives the measurements.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np

from fedmap.errors import FedmapError
from fedmap.maps.georef import cell_centre, local_transform
from fedmap.maps.grid import PALETTE, GridMap
from fedmap.maps.ros import lower_left_origin
from fedmap.mission.network.link import BASE
from fedmap.mission.results import Snapshot
from fedmap.mission.settings import MissionConfig

#: Seconds of message time per mission step.
STEP_SECONDS = 1.0
_STEP_NS = int(STEP_SECONDS * 1e9)
#: The frame every map, pose and scene entity is in, and its parent (the CRS origin).
MAP_FRAME, CRS_FRAME = "map", "crs"
#: Colours of the members of the team (RGB in [0, 1]), in team order, repeating.
MEMBER_COLOURS = ((0.12, 0.47, 0.71), (1.0, 0.5, 0.05), (0.58, 0.4, 0.74), (0.09, 0.75, 0.81),
                  (0.89, 0.47, 0.76), (0.74, 0.74, 0.13))
_FOOTPRINT_POINTS = 24
_FM: Any = None


def _fm() -> Any:
    """``foxglove.messages``, imported once (on first use: importing fedmap stays free of it)."""
    global _FM
    if _FM is None:
        import foxglove.messages

        _FM = foxglove.messages
    return _FM

_LINK_SCHEMA: dict[str, Any] = {
    "title": "fedmap.LinkMessage", "type": "object",
    "description": ("One ledger entry of the link: who sent what, its bytes and its fate "
                    "(fedmap.mission.network.link.Message)."),
    "properties": {
        "round": {"type": "integer"}, "step": {"type": "integer", "description": "when it was sent"},
        "rover": {"type": "integer"}, "direction": {"type": "string", "description": "up, down or peer"},
        "kind": {"type": "string"}, "bytes": {"type": "integer", "description": "bytes spent on the link"},
        "status": {"type": "string", "description": "delivered, lost, over budget, out of range, link down, ..."},
        "arrival": {"type": ["integer", "null"]}, "to": {"type": ["integer", "null"]},
        "sender": {"type": "integer", "description": "who spent the bytes (-1: the base or lander)"},
    },
}
_NUMBERS = {"type": "array", "items": {"type": ["number", "null"]}}
_STEP_SCHEMA: dict[str, Any] = {
    "title": "fedmap.StepScores", "type": "object",
    "description": "One step's scores (fedmap.mission.results.StepRow), per member in team order, plus team totals.",
    "properties": {
        "step": {"type": "integer"}, "coverage": {"type": "number"}, "redundant": {"type": "number"},
        **{k: _NUMBERS for k in ("accuracy", "accuracy_observed", "accuracy_unobserved", "false_free", "distance",
                                 "bytes_up", "bytes_down")},
        **{k: {"type": "integer"} for k in ("up_delivered", "up_dropped", "down_delivered", "down_dropped",
                                            "bytes_up_total", "bytes_down_total", "bytes_total")},
        "accuracy_mean": {"type": "number"}, "false_free_mean": {"type": "number"},
    },
}
_EVAL_SCHEMA: dict[str, Any] = {
    "title": "fedmap.EvalScores", "type": "object",
    "description": "One evaluation step's map scores (fedmap.mission.results.EvalRow); null: not finite.",
    "properties": {
        "step": {"type": "integer"},
        **{k: {"type": ["number", "null"]} for k in ("psnr", "ssim", "accuracy", "f1", "f1_tolerant",
                                                     "belief_f1_mean")},
        "belief_f1": _NUMBERS, "belief_success": _NUMBERS,
    },
}


def topics(config: MissionConfig) -> list[str]:
    """Every topic a recording of ``config`` has, in the order they are declared."""
    members = config.rovers + config.helicopters
    out = ["/tf", "/truth"]
    for s in config.strategies:
        out += [*(f"/{s}/belief/{k}" for k in range(members)), f"/{s}/global_map", f"/{s}/scene", f"/{s}/poses",
                f"/{s}/link", f"/{s}/scores", f"/{s}/eval"]
    return out


def cell_xy(cell: tuple[int, int], shape: tuple[int, int], pixel_size: float) -> tuple[float, float]:
    """The ``map``-frame (x, y) in metres of the centre of ``cell`` (row, col): the ``map`` frame
    is :func:`~fedmap.maps.georef.local_transform`'s (the lower-left corner at 0, 0)."""
    return cell_centre(local_transform(pixel_size, shape), *cell)


def xy_cell(x: float, y: float, shape: tuple[int, int], pixel_size: float) -> tuple[int, int]:
    """The cell (row, col) whose centre is at ``map``-frame (x, y) metres (:func:`cell_xy` inverted)."""
    return int(round(shape[0] - y / pixel_size - 0.5)), int(round(x / pixel_size - 0.5))


def _finite(v: Any) -> Any:
    """``v`` for JSON: tuples as lists, non-finite floats as None (JSON has no NaN or infinity)."""
    if isinstance(v, (list, tuple)):
        return [_finite(x) for x in v]
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


def _flat(row: Any) -> dict:
    """A flat dataclass (a StepRow, an EvalRow) as a dict, without ``asdict``'s deep copies."""
    return {f.name: getattr(row, f.name) for f in fields(row)}


def _json(d: dict) -> bytes:
    return json.dumps({k: _finite(v) for k, v in d.items()}, allow_nan=False, separators=(",", ":")).encode()


@dataclass
class _Out:
    """One destination (the MCAP file or the live server): its context, channels and clock."""

    context: Any
    channels: dict[str, Any]
    sequential: bool  # strategies follow one another on the clock, and static topics repeat per strategy
    sink: Any = None  # the MCAPWriter or WebSocketServer


def _stamp(ns: int) -> Any:
    return _fm().Timestamp(sec=ns // 1_000_000_000, nsec=ns % 1_000_000_000)


class Scene:
    """What the 3D panel draws of a mission on a map of ``shape`` cells of ``pixel_size``
    metres: every member's pose, and the scene of members, trails, targets, footprints,
    base, links and leaders."""

    def __init__(self, shape: tuple[int, int], pixel_size: float) -> None:
        self.shape, self.pixel_size = shape, pixel_size
        self._rings: dict[float, list[Any]] = {}

    def poses(self, snap: Snapshot, ns: int) -> Any:
        """Every member's pose in the ``map`` frame (metres; helicopters at :func:`_height`)."""
        Pose, PosesInFrame = _fm().Pose, _fm().PosesInFrame
        return PosesInFrame(timestamp=_stamp(ns), frame_id=MAP_FRAME, poses=[
            Pose(position=_vec(*cell_xy(p, self.shape, self.pixel_size), self._height(kind)), orientation=_quat())
            for p, kind in zip(snap.positions, snap.kinds)])

    def _ring(self, r: float) -> list[Any]:
        """The points of a circle of radius ``r`` metres around the origin (cached by radius)."""
        if r not in self._rings:
            a = np.linspace(0, 2 * np.pi, _FOOTPRINT_POINTS, endpoint=False)
            self._rings[r] = [_pt(r * math.cos(t), r * math.sin(t), 0.0) for t in a]
        return self._rings[r]

    def _height(self, kind: str) -> float:
        """A member's drawn height above the map: 0 for a rover, 3 cells for a helicopter."""
        return 3.0 * self.pixel_size if kind == "helicopter" else 0.0

    def scene(self, snap: Snapshot, trails: list[list[Any]], ns: int) -> Any:
        """The ``/<s>/scene`` SceneUpdate: members, trails, targets, footprints, base, links, leaders."""
        m = _fm()
        CubePrimitive, LinePrimitive, LinePrimitiveLineType, Pose = m.CubePrimitive, m.LinePrimitive, \
            m.LinePrimitiveLineType, m.Pose
        SceneEntity, SceneUpdate, SpherePrimitive, TextPrimitive = m.SceneEntity, m.SceneUpdate, m.SpherePrimitive, \
            m.TextPrimitive

        ps, stamp = self.pixel_size, _stamp(ns)
        xy = [cell_xy(p, self.shape, ps) for p in snap.positions]

        def entity(name: str, **prims: Any) -> Any:
            return SceneEntity(timestamp=stamp, frame_id=MAP_FRAME, id=name, frame_locked=True, **prims)

        def at(x: float, y: float, z: float = 0.0) -> Any:
            return Pose(position=_vec(x, y, z), orientation=_quat())

        ents = []
        for k, ((x, y), kind, target, radius) in enumerate(zip(xy, snap.kinds, snap.targets, snap.sensor_radius)):
            tint = MEMBER_COLOURS[k % len(MEMBER_COLOURS)]
            colour = _colour(*tint)
            z = self._height(kind)
            size = _vec(2 * ps, 2 * ps, 2 * ps if kind == "helicopter" else ps)
            body = {"spheres": [SpherePrimitive(pose=at(x, y, z), size=size, color=colour)]} if kind == "helicopter" \
                else {"cubes": [CubePrimitive(pose=at(x, y, z + ps / 2), size=size, color=colour)]}
            ents.append(entity(f"member/{k}", **body, texts=[TextPrimitive(
                pose=at(x, y, z + 3 * ps), billboard=True, font_size=12.0, scale_invariant=True,
                color=_colour(1, 1, 1), text=f"{kind} {k}" + (" (leader)" if k in snap.leaders else ""))]))
            ents.append(entity(f"trail/{k}", lines=[LinePrimitive(
                type=LinePrimitiveLineType.LineStrip, thickness=2.0, scale_invariant=True, points=list(trails[k]),
                color=_colour(*tint, a=0.8))]))
            ents.append(entity(f"footprint/{k}", lines=[LinePrimitive(
                type=LinePrimitiveLineType.LineLoop, pose=at(x, y, 0.05), thickness=1.5, scale_invariant=True,
                points=self._ring(radius * ps), color=_colour(1, 1, 1, a=0.9))]))
            if target is None:
                ents.append(entity(f"target/{k}"))  # no primitives: nothing drawn
            else:
                tx, ty = cell_xy(target, self.shape, ps)
                ents.append(entity(f"target/{k}", spheres=[SpherePrimitive(
                    pose=at(tx, ty), size=_vec(ps, ps, ps), color=colour)], lines=[LinePrimitive(
                        type=LinePrimitiveLineType.LineList, thickness=1.0, scale_invariant=True,
                        points=[_pt(x, y, 0.1), _pt(tx, ty, 0.1)], color=_colour(*tint, a=0.5))]))
        bx, by = cell_xy(snap.base, self.shape, ps)
        ents.append(entity("base", cubes=[CubePrimitive(pose=at(bx, by, ps), size=_vec(3 * ps, 3 * ps, 2 * ps),
                                                        color=_colour(0.1, 0.1, 0.1))]))
        where = {**dict(enumerate(xy)), BASE: (bx, by)}
        points = [_pt(*where[i], 0.2) for a, b in snap.links for i in (a, b) if a in where and b in where]
        ents.append(entity("links", lines=[LinePrimitive(
            type=LinePrimitiveLineType.LineList, thickness=2.0, scale_invariant=True, points=points,
            color=_colour(1, 1, 1, a=0.8))] if points else None))
        ents.append(entity("leaders", spheres=[SpherePrimitive(
            pose=at(*where[a], 0.0), size=_vec(5 * ps, 5 * ps, 0.5 * ps), color=_colour(0, 0, 0, a=0.4))
            for a in snap.leaders if a in where] or None))
        return SceneUpdate(entities=ents)


class Recorder:
    """Records a mission's snapshots as Foxglove messages (module docstring): pass it as
    ``run_mission(..., on_snapshot=recorder)`` (or to ``run_repeats``), then :meth:`close` it
    (or use it as a context manager).

    ``mcap``: the MCAP file to write (replaced atomically when the recorder closes; None:
    none). ``live``: also start a Foxglove WebSocket server on ``host:port`` (0: a free port;
    :attr:`url` is its ``ws://`` address) that streams the same channels as the mission
    runs. ``elevation``: the truth's heights (metres, its grid) for ``/truth``'s elevation
    field. Every channel exists from the start, so a client can subscribe before the
    mission runs.
    """

    def __init__(self, config: MissionConfig, truth: GridMap, *, mcap: str | os.PathLike | None = None,
                 live: bool = False, host: str = "127.0.0.1", port: int = 8765,
                 elevation: np.ndarray | None = None) -> None:
        import foxglove

        if mcap is None and not live:
            raise FedmapError("a recorder needs an MCAP path, a live server, or both")
        self.config, self.truth, self.host = config, truth, host
        self.shape, self.pixel_size = truth.shape, float(truth.pixel_size)
        self.elevation = None if elevation is None else np.asarray(elevation, dtype=np.float32)
        if self.elevation is not None and self.elevation.shape != truth.shape:
            raise FedmapError(f"elevation grid {self.elevation.shape} does not match the map {truth.shape}")
        self.closed = False
        self.path = None if mcap is None else Path(mcap)
        self._tmp: Path | None = None
        self.outs: list[_Out] = []
        self.server: Any = None
        if self.path is not None:
            check_recording_path(self.path)
            self._tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}.tmp")
            ctx = foxglove.Context()
            out = _Out(ctx, self._channels(ctx), sequential=False)
            try:
                out.sink = foxglove.open_mcap(self._tmp, allow_overwrite=True, context=ctx)
            except Exception as exc:  # the SDK raises its own error types (an unwritable folder)
                raise FedmapError(f"cannot record to {self.path}: {' '.join(str(exc).split())}") from exc
            self.outs.append(out)
        if live:
            ctx = foxglove.Context()
            out = _Out(ctx, self._channels(ctx), sequential=True)
            try:
                out.sink = self.server = foxglove.start_server(name="fedmap mission", host=host, port=port,
                                                               context=ctx)
            except Exception as exc:  # the SDK raises its own error types (e.g. the port is taken)
                self.close(keep=False)
                raise FedmapError(f"cannot start the live server on {host}:{port}: "
                                  f"{' '.join(str(exc).split())}") from exc
            self.outs.append(out)
        self._index = {s: i for i, s in enumerate(config.strategies)}
        self._started: set[str] = set()
        self._last: dict[str, np.ndarray] = {}  # topic -> the array last logged on it
        self._trails: dict[str, list[list[Any]]] = {}
        self.drawing = Scene(self.shape, self.pixel_size)
        self._lut = np.concatenate([np.arange(3, dtype=np.uint8)[:, None],
                                    np.round(PALETTE * 255).astype(np.uint8),
                                    np.full((3, 1), 255, dtype=np.uint8)], axis=1)  # class -> classes, r, g, b, a

    # --- channels -------------------------------------------------------------------------
    def _channels(self, ctx: Any) -> dict[str, Any]:
        import foxglove
        from foxglove import channels as fc

        json_schemas = {"link": _LINK_SCHEMA, "scores": _STEP_SCHEMA, "eval": _EVAL_SCHEMA}
        out: dict[str, Any] = {}
        for topic in topics(self.config):
            leaf = topic.rsplit("/", 1)[-1]
            if topic == "/tf":
                out[topic] = fc.FrameTransformsChannel(topic, context=ctx)
            elif topic == "/truth" or "/belief/" in topic or leaf == "global_map":
                out[topic] = fc.GridChannel(topic, context=ctx)
            elif leaf == "scene":
                out[topic] = fc.SceneUpdateChannel(topic, context=ctx)
            elif leaf == "poses":
                out[topic] = fc.PosesInFrameChannel(topic, context=ctx)
            else:
                schema = json_schemas[leaf]
                out[topic] = foxglove.Channel(topic, message_encoding="json", context=ctx, schema=foxglove.Schema(
                    name=schema["title"], encoding="jsonschema", data=json.dumps(schema).encode()))
        return out

    @property
    def url(self) -> str | None:
        """The live server's ``ws://`` address (None: no live server)."""
        return None if self.server is None else f"ws://{self.host}:{self.server.port}"

    def app_url(self) -> str | None:
        """A Foxglove app link that opens the live server (None: no live server)."""
        return None if self.server is None else self.server.app_url()

    # --- messages -------------------------------------------------------------------------
    def grid(self, classes: np.ndarray, heights: np.ndarray | None, ns: int) -> Any:
        """The ``foxglove.Grid`` of a class map (and its heights) at message time ``ns``."""
        m = _fm()
        u8, f32 = m.PackedElementFieldNumericType.Uint8, m.PackedElementFieldNumericType.Float32
        cells = np.take(self._lut, np.asarray(classes)[::-1], axis=0)  # (H, W, 5), bottom row first
        fields = [m.PackedElementField(name=n, offset=i, type=u8)
                  for i, n in enumerate(("classes", "red", "green", "blue", "alpha"))]
        if heights is not None:
            z = np.ascontiguousarray(np.asarray(heights, dtype="<f4")[::-1])
            cells = np.concatenate([cells, z.view(np.uint8).reshape(*z.shape, 4)], axis=2)
            fields.append(m.PackedElementField(name="elevation", offset=5, type=f32))
        h, w, stride = cells.shape
        return m.Grid(timestamp=_stamp(ns), frame_id=MAP_FRAME, pose=m.Pose(position=_vec(0, 0, 0),
                                                                                   orientation=_quat()),
                      column_count=w, cell_size=m.Vector2(x=self.pixel_size, y=self.pixel_size), row_stride=w * stride,
                      cell_stride=stride, fields=fields, data=cells.tobytes())

    def _static(self, out: _Out, ns: int) -> None:
        FrameTransform, FrameTransforms = _fm().FrameTransform, _fm().FrameTransforms
        x0, y0 = lower_left_origin(self.truth)  # the map frame's origin in the crs frame
        out.channels["/tf"].log(FrameTransforms(transforms=[FrameTransform(
            timestamp=_stamp(ns), parent_frame_id=CRS_FRAME, child_frame_id=MAP_FRAME,
            translation=_vec(x0, y0, 0.0), rotation=_quat())]), log_time=ns)
        out.channels["/truth"].log(self.grid(self.truth.classes, self.elevation, ns), log_time=ns)

    def __call__(self, snap: Snapshot) -> None:
        """Log one snapshot (the ``on_snapshot`` callback)."""
        self.log(snap)

    def log(self, snap: Snapshot) -> None:
        """Log one snapshot on every destination."""
        if self.closed:
            raise FedmapError("this recorder is closed")
        s, t = snap.strategy, snap.step
        if s not in self._index:
            raise FedmapError(f"strategy {s!r} is not one of the recorded mission's ({', '.join(self._index)})")
        first = s not in self._started
        if first:
            self._started.add(s)
            self._trails[s] = [[] for _ in snap.positions]
        starts = {id(o): self._index[s] * (self.config.steps + 1) * _STEP_NS if o.sequential else 0
                  for o in self.outs}
        for o in self.outs:
            if first and (o.sequential or len(self._started) == 1):
                self._static(o, starts[id(o)])
        # maps: only when they changed since they were last logged on the topic
        maps: list[tuple[str, np.ndarray, np.ndarray | None]] = [
            (f"/{s}/belief/{k}", b, None) for k, b in enumerate(snap.beliefs)]
        maps.append((f"/{s}/global_map", snap.global_map, snap.global_heights))
        for topic, classes, heights in maps:
            last, last_z = self._last.get(topic), self._last.get(topic + "#z")
            if last is not None and np.array_equal(last, classes) and (
                    heights is None or (last_z is not None and np.array_equal(last_z, heights, equal_nan=True))):
                continue
            self._last[topic] = np.array(classes, copy=True)
            if heights is not None:
                self._last[topic + "#z"] = np.array(heights, copy=True)
            for o in self.outs:
                ns = starts[id(o)] + t * _STEP_NS
                o.channels[topic].log(self.grid(classes, heights, ns), log_time=ns)
        trails = self._trails[s]
        for k, p in enumerate(snap.positions):
            trails[k].append(_pt(*cell_xy(p, self.shape, self.pixel_size), 0.0))
        for o in self.outs:
            ns = starts[id(o)] + t * _STEP_NS
            o.channels[f"/{s}/scene"].log(self.drawing.scene(snap, trails, ns), log_time=ns)
            o.channels[f"/{s}/poses"].log(self.drawing.poses(snap, ns), log_time=ns)
            for m in snap.messages:
                o.channels[f"/{s}/link"].log(_json({**m.to_dict(), "sender": m.sender}), log_time=ns)
            o.channels[f"/{s}/scores"].log(self.scores(snap), log_time=ns)
            if snap.eval is not None:
                e = _flat(snap.eval)
                e["belief_f1_mean"] = float(np.mean(snap.eval.belief_f1)) if snap.eval.belief_f1 else None
                o.channels[f"/{s}/eval"].log(_json(e), log_time=ns)

    @staticmethod
    def scores(snap: Snapshot) -> bytes:
        """The ``/<s>/scores`` JSON of a snapshot."""
        r = snap.row
        d = _flat(r)
        up, down = int(sum(r.bytes_up)), int(sum(r.bytes_down))
        d.update(bytes_up_total=up, bytes_down_total=down, bytes_total=up + down,
                 accuracy_mean=float(np.mean(r.accuracy)) if r.accuracy else None,
                 false_free_mean=float(np.mean(r.false_free)) if r.false_free else None)
        return _json(d)

    # --- closing --------------------------------------------------------------------------
    def close(self, *, keep: bool = True) -> None:
        """Stop the live server and finish the MCAP (renamed into place; ``keep=False``: removed)."""
        if self.closed:
            return
        self.closed = True
        for o in self.outs:
            if o.sink is self.server and o.sink is not None:
                o.sink.stop()
            elif o.sink is not None:
                o.sink.close()
        if self._tmp is not None and self.path is not None:
            if keep and self._tmp.exists():
                os.replace(self._tmp, self.path)
            else:
                self._tmp.unlink(missing_ok=True)

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, exc_type: Any, *_: Any) -> None:
        self.close(keep=exc_type is None)


def _vec(x: float, y: float, z: float) -> Any:
    return _fm().Vector3(x=float(x), y=float(y), z=float(z))


def _pt(x: float, y: float, z: float) -> Any:
    return _fm().Point3(x=float(x), y=float(y), z=float(z))


def _quat() -> Any:
    return _fm().Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)


def _colour(r: float, g: float, b: float, a: float = 1.0) -> Any:
    return _fm().Color(r=r, g=g, b=b, a=a)


# --- the Foxglove layout ------------------------------------------------------------------
def _three_d(topics_on: dict[str, str], centre: tuple[float, float], span: float) -> dict:
    """A 3D panel looking straight down on the ``map`` frame at ``centre`` showing ``topics_on``."""
    grid = {"visible": True, "colorMode": "rgba-fields", "frameLocked": True}
    return {"cameraState": {"perspective": False, "distance": span * 1.4, "phi": 0, "thetaOffset": 0,
                            "targetOffset": [centre[0], centre[1], 0], "target": [0, 0, 0],
                            "targetOrientation": [0, 0, 0, 1], "fovy": 45, "near": 0.5, "far": 5000},
            "followMode": "follow-none", "followTf": MAP_FRAME, "scene": {"enableStats": False},
            "transforms": {}, "layers": {}, "publish": {}, "imageMode": {},
            "topics": {t: grid if kind == "grid" else {"visible": True} for t, kind in topics_on.items()}}


def _row(panels: list[str]) -> Any:
    """A mosaic row of equally wide panels."""
    if len(panels) == 1:
        return panels[0]
    return {"first": panels[0], "second": _row(panels[1:]), "direction": "row",
            "splitPercentage": round(100 / len(panels), 2)}


def foxglove_layout(strategies: tuple[str, ...] | list[str], members: int, shape: tuple[int, int],
                    pixel_size: float = 1.0) -> dict:
    """A Foxglove layout (the app's *Import from file* JSON: ``configById`` and a mosaic
    ``layout``) that shows a recording as the mission's GIF does, one tab per strategy:
    truth | each member's belief | global map with the rovers, trails, footprints, links and
    leaders; under it the scores over time (coverage, mean belief accuracy, team bytes, global
    path F1 at the evaluation steps) of every strategy, and the link messages of the tab's
    strategy. ``docs/foxglove_layout.json`` is this layout for the default mission."""
    h, w = shape
    centre, span = (w * pixel_size / 2, h * pixel_size / 2), max(h, w) * pixel_size
    config: dict[str, Any] = {}
    tabs = []
    for s in strategies:
        ids = [f"3D!{s}-truth"]
        config[ids[0]] = _three_d({"/truth": "grid"}, centre, span)
        for k in range(members):
            ids.append(f"3D!{s}-belief-{k}")
            config[ids[-1]] = _three_d({f"/{s}/belief/{k}": "grid", f"/{s}/scene": "scene"}, centre, span)
        ids.append(f"3D!{s}-global")
        config[ids[-1]] = _three_d({f"/{s}/global_map": "grid", f"/{s}/scene": "scene"}, centre, span)
        config[f"RawMessages!{s}-link"] = {"topicPath": f"/{s}/link", "diffEnabled": False, "diffMethod": "custom",
                                          "diffTopicPath": "", "showFullMessageForDiff": False, "expansion": "all"}
        tabs.append({"title": s, "layout": {"first": _row(ids), "second": f"RawMessages!{s}-link",
                                            "direction": "column", "splitPercentage": 80}})
    config["Tab!strategies"] = {"activeTabIdx": 0, "tabs": tabs}
    plots = {"coverage": "scores.coverage", "belief-accuracy": "scores.accuracy_mean",
             "team-bytes": "scores.bytes_total", "global-f1": "eval.f1"}
    for name, path in plots.items():
        config[f"Plot!{name}"] = {
            "title": name.replace("-", " "), "paths": [{"value": f"/{s}/{path}", "enabled": True,
                                                        "timestampMethod": "receiveTime", "label": s}
                                                       for s in strategies],
            "showXAxisLabels": True, "showYAxisLabels": True, "showLegend": True, "legendDisplay": "floating",
            "showPlotValuesInLegend": True, "isSynced": True, "xAxisVal": "timestamp", "sidebarDimension": 240}
    return {"configById": config, "globalVariables": {}, "userNodes": {}, "playbackConfig": {"speed": 1},
            "layout": {"first": "Tab!strategies", "second": _row([f"Plot!{n}" for n in plots]),
                       "direction": "column", "splitPercentage": 65}}


# --- reading back ---------------------------------------------------------------------------
@dataclass(frozen=True)
class Recorded:
    """One message of a recording: its topic, schema, encoding, log time (ns) and payload."""

    topic: str
    schema: str
    encoding: str  #: ``protobuf`` (Foxglove's typed messages) or ``json``
    log_time: int
    data: bytes


#: The first bytes of every MCAP file (the format's magic).
MCAP_MAGIC = b"\x89MCAP0\r\n"


def check_recording_path(path: str | os.PathLike) -> Path:
    """Where a recording goes, checked before any work: a new file, or an earlier MCAP
    recording (which is replaced), in a folder that exists. A folder, or a file of anything
    else (the user's own), is a one-line error: it is never overwritten."""
    p = Path(path)
    if p.is_dir():
        raise FedmapError(f"--record {p} is a folder; give the MCAP file's path")
    if not p.parent.is_dir():
        raise FedmapError(f"cannot record to {p}: folder {p.parent} does not exist")
    if p.exists():
        try:
            with open(p, "rb") as fh:
                head = fh.read(len(MCAP_MAGIC))
        except OSError as exc:
            raise FedmapError(f"cannot record to {p}: {exc.strerror or exc}") from None
        if head != MCAP_MAGIC:
            raise FedmapError(f"--record {p} exists and is not an MCAP recording; a recording replaces only an "
                              "earlier one: give a new path")
    return p


def read_recording(path: str | os.PathLike) -> tuple[list[Recorded], dict[str, bytes]]:
    """Every message of an MCAP recording in file order, and each schema's data by name (a
    protobuf ``FileDescriptorSet`` or a JSON schema). A truncated or unreadable file raises
    a one-line :class:`FedmapError`."""
    from mcap.exceptions import McapError
    from mcap.reader import make_reader

    p = Path(path)
    try:
        f = open(p, "rb")
    except OSError as exc:
        raise FedmapError(f"cannot read recording {p}: {exc.strerror or exc}") from exc
    out, schemas = [], {}
    try:
        with f:
            for schema, channel, message in make_reader(f).iter_messages(log_time_order=False):
                name = schema.name if schema is not None else ""
                if schema is not None:
                    schemas[name] = schema.data
                out.append(Recorded(channel.topic, name, channel.message_encoding, message.log_time,
                                    bytes(message.data)))
    except (McapError, OSError, EOFError, ValueError, KeyError, IndexError) as exc:  # what a cut file raises
        raise FedmapError(f"{p} is not a complete MCAP recording ({type(exc).__name__}: "
                          f"{' '.join(str(exc).split())[:120]})") from exc
    return out, schemas


def decode(message: Recorded, schemas: dict[str, bytes]) -> dict:
    """A recorded message as a dict: JSON parsed, protobuf decoded with the schema in the file
    (needs the ``protobuf`` package, which Flower brings; field names as in the schema)."""
    if message.encoding == "json":
        return json.loads(message.data)
    if message.encoding != "protobuf":
        raise FedmapError(f"{message.topic}: cannot decode message encoding {message.encoding!r}")
    try:
        from google.protobuf import descriptor_pb2, descriptor_pool, json_format, message_factory
    except ImportError as exc:
        raise FedmapError("decoding Foxglove's protobuf messages needs the protobuf package "
                          "(pip install protobuf)") from exc
    cls = _PROTO_CLASSES.get(message.schema)
    if cls is None:
        fds = descriptor_pb2.FileDescriptorSet.FromString(schemas[message.schema])
        pool = descriptor_pool.DescriptorPool()
        for fd in fds.file:
            pool.Add(fd)
        cls = _PROTO_CLASSES[message.schema] = message_factory.GetMessageClass(
            pool.FindMessageTypeByName(message.schema))
    return json_format.MessageToDict(cls.FromString(message.data), preserving_proto_field_name=True,
                                     always_print_fields_with_no_presence=True)


_PROTO_CLASSES: dict[str, Any] = {}


def grid_arrays(grid: dict) -> dict[str, np.ndarray]:
    """A decoded ``foxglove.Grid``'s fields as ``(H, W)`` arrays, row 0 at the top (north) as
    fedmap keeps grids: ``{"classes": ..., "red": ..., "elevation": ...}``."""
    import base64

    data = base64.b64decode(grid["data"]) if isinstance(grid["data"], str) else bytes(grid["data"])
    w, cs, rs = int(grid["column_count"]), int(grid["cell_stride"]), int(grid["row_stride"])
    h = len(data) // rs
    raw = np.frombuffer(data, dtype=np.uint8).reshape(h, rs)[:, : w * cs].reshape(h, w, cs)
    kinds = {"UINT8": ("u1", 1), "FLOAT32": ("<f4", 4), 1: ("u1", 1), 7: ("<f4", 4)}
    out = {}
    for f in grid["fields"]:
        dtype, size = kinds[f["type"]]
        o = int(f.get("offset", 0))
        out[f["name"]] = np.ascontiguousarray(raw[:, :, o:o + size]).view(dtype).reshape(h, w)[::-1]
    return out


__all__ = ["CRS_FRAME", "MAP_FRAME", "MEMBER_COLOURS", "STEP_SECONDS", "Recorded", "Recorder", "cell_xy", "decode",
           "foxglove_layout", "grid_arrays", "read_recording", "topics", "xy_cell"]
