"""The base station: a Flower ``ServerApp`` running fedmap's strategy for R rounds.

:class:`FedmapStrategy` is a Flower ``Strategy`` whose aggregation is
:func:`fedmap.federation.runner.base_step` (fedmap's FedAvg / FedAdam / FedYogi /
coverage math), so a run equals :func:`~fedmap.federation.runner.run_federation` for the
same seed and settings. ``strategy.start`` drives the rounds; the run config's
``deadline`` is the per-round timeout, so a rover that never replies cannot hang the
base: the round aggregates the survivors and records who was missing and why.

While the run goes, ``<out>.run/`` holds ``status.json`` (state, round, message) and an
atomic checkpoint ``global_model_round{r}.safetensors`` after every round; at the end the
checkpoints move into ``<out>/`` beside the demo's outputs.
"""

from __future__ import annotations

import json
import os
import time
from logging import INFO
from pathlib import Path

from flwr.app import ArrayRecord, ConfigRecord, Context, Message, MessageType, MetricRecord, RecordDict
from flwr.serverapp import Grid, ServerApp
from flwr.serverapp.strategy import Strategy
from flwr.supercore import log

from fedmap.comm import CodecSpec, Encoder
from fedmap.errors import FedmapError
from fedmap.federation.aggregate import make_aggregator
from fedmap.federation.flower.records import check_flower_count, from_record, to_record
from fedmap.federation.flower.settings import RunSettings, load_truth, run_dir, run_status_path
from fedmap.federation.runner import FederationResult, base_step, round_record
from fedmap.model import Weights, build_model, get_weights, preset, save_model, set_weights

app = ServerApp()


def write_status(out_dir: Path, state: str, **fields) -> None:
    from fedmap.maps.io import atomic_write_bytes

    atomic_write_bytes(run_status_path(out_dir), json.dumps({"state": state, **fields}).encode())


class FedmapStrategy(Strategy):
    """fedmap's rounds on Flower: payloads in, ``base_step`` aggregation, broadcast out.

    Parameters
    ----------
    settings : RunSettings
        Rounds, aggregator, codecs, rovers / min-rovers, deadline, ...
    sleep : callable
        Used while waiting for rovers to connect (tests pass a fake clock).
    """

    def __init__(self, settings: RunSettings, *, sleep=time.sleep) -> None:
        self.settings = settings
        fed = settings.federation
        self.aggregator = make_aggregator(fed.aggregator, eta=fed.eta, beta1=fed.beta1, beta2=fed.beta2, tau=fed.tau)
        self.up_spec, self.down_spec = CodecSpec.parse(fed.uplink), CodecSpec.parse(fed.downlink)
        self.down_encoder = Encoder(self.down_spec)
        self.held: Weights | None = None  # what every rover holds; the initial model until round 1 ends
        self.shape: tuple[int, int] | None = None
        self.history: list[dict] = []
        self.node_partition: dict[int, int] = {}  # Flower node id -> rover index
        self._sleep = sleep
        self._t0 = 0.0
        self._sent: dict[str, int] = {}  # message id -> node id of the last messages sent

    # -- helpers ---------------------------------------------------------------------------

    def _wait_for_nodes(self, grid: Grid, want: int) -> list[int]:
        """Connected node ids once ``want`` are there or ``connect_timeout`` has passed."""
        s = self.settings
        t_end = time.monotonic() + s.connect_timeout
        while len(nodes := sorted(grid.get_node_ids())) < want and time.monotonic() < t_end:
            self._sleep(0.5)
        if len(nodes) < s.min_rovers:
            raise FedmapError(f"only {len(nodes)} rover(s) connected after {s.connect_timeout:g} s, "
                              f"fewer than min-rovers={s.min_rovers}; start more rovers or lower min-rovers")
        return nodes

    def _messages(self, nodes: list[int], arrays: ArrayRecord, kind: str, server_round: int) -> list[Message]:
        payload = from_record(arrays)
        if self.history:  # the previous round's broadcast goes out now: book it per rover
            flower = check_flower_count(arrays, len(payload))
            rec = self.history[-1]
            for n in nodes:
                who = self.node_partition.get(n, f"node-{n}")
                rec["downlink_bytes"][who] = len(payload)
                rec["flower_downlink_bytes"][who] = flower
        content = RecordDict({"downlink": arrays, "config": ConfigRecord({"server-round": server_round})})
        msgs = [Message(content, dst_node_id=n, message_type=kind) for n in nodes]
        # Flower's message id is the object id (set when pushed); error replies made by the
        # SuperLink (e.g. "node unavailable") come from the SuperLink's own node id, so the
        # rover they concern is found through the message they reply to
        self._sent = {m.object_id: n for m, n in zip(msgs, nodes)}
        return msgs

    def initial_weights(self, height: int) -> Weights:
        """The initial model every rover rebuilds from the shared seed (never sent)."""
        from fedmap.pipeline import initial_model

        s = self.settings
        return get_weights(initial_model(preset(s.net, height), init=s.init, seed=s.federation.seed,
                                         prior_steps=s.prior_steps))

    # -- Strategy --------------------------------------------------------------------------

    def configure_train(self, server_round: int, arrays: ArrayRecord, config: ConfigRecord, grid: Grid) -> list[Message]:
        s = self.settings
        nodes = self._wait_for_nodes(grid, s.rovers if server_round == 1 else s.min_rovers)
        log(INFO, "fedmap: round %d: sending to %d rover(s)", server_round, len(nodes))
        write_status(s.out, "running", round=server_round, nodes=len(nodes))
        self._t0 = time.perf_counter()
        return self._messages(nodes, arrays, MessageType.TRAIN, server_round)

    def aggregate_train(self, server_round: int, replies) -> tuple[ArrayRecord | None, MetricRecord | None]:
        s = self.settings
        payloads, counts, losses, dropped, flower_up, node_errors = {}, {}, {}, {}, {}, {}
        for msg in replies:
            node = self._sent.get(msg.metadata.reply_to_message_id, msg.metadata.src_node_id)
            if msg.has_error():  # the ClientApp crashed or the node went away
                pid = self.node_partition.get(node)
                reason = f"Flower error {msg.error.code}: {msg.error.reason}".splitlines()[0]
                if pid is None:
                    node_errors[str(node)] = reason
                else:
                    dropped[pid] = reason
                continue
            met = msg.content["metrics"]
            pid = int(met["partition-id"])
            self.node_partition[node] = pid
            shape = (int(met["height"]), int(met["width"]))
            if self.shape is None:
                self.shape = shape
            elif shape != self.shape:
                dropped[pid] = f"its map is {shape[0]}x{shape[1]}, the team's is {self.shape[0]}x{self.shape[1]}"
                continue
            if "error" in msg.content.config_records:
                dropped[pid] = str(msg.content["error"]["reason"])
                continue
            record = msg.content["uplink"]
            payloads[pid] = from_record(record)
            flower_up[pid] = check_flower_count(record, len(payloads[pid]))
            counts[pid] = float(met["known-cells"])
            losses[pid] = float(met["loss"]) if "loss" in met else None
        missing = sorted(set(range(s.rovers)) - set(payloads) - set(dropped))
        if len(payloads) < s.min_rovers:
            raise FedmapError(
                f"round {server_round}: {len(payloads)} rover(s) delivered an update, fewer than min-rovers="
                f"{s.min_rovers} (missing: {missing or 'none'}; dropped: {dropped or 'none'})")
        if self.held is None:
            self.held = self.initial_weights(self.shape[0])
        step = base_step(self.aggregator, self.held, payloads, counts, self.down_encoder, dropped=dropped,
                         round_label=server_round)
        self.held = step.held
        rec = round_record(server_round, step, losses, {k: len(p) for k, p in sorted(payloads.items())}, {},
                           self.up_spec, self.down_spec, time.perf_counter() - self._t0)
        rec.update(missing=missing, node_errors=node_errors, flower_uplink_bytes=dict(sorted(flower_up.items())),
                   flower_downlink_bytes={})
        self.history.append(rec)
        log(INFO, "fedmap: round %d aggregated %d rover(s); missing %s; dropped %s", server_round,
            len(step.counts), missing, list(step.dropped))
        return to_record(step.downlink), MetricRecord({"rovers-used": len(step.counts),
                                                       "uplink-bytes": sum(rec["uplink_bytes"].values())})

    def configure_evaluate(self, server_round: int, arrays: ArrayRecord, config: ConfigRecord, grid: Grid) -> list[Message]:
        if server_round < self.settings.federation.rounds:
            return []  # broadcasts ride on the next round's train messages
        # the final model goes to the rovers that took part in the last round: a rover that
        # died may still be listed as connected, and waiting for it would cost a deadline
        last = set(self.history[-1]["weights"]) if self.history else set()
        nodes = sorted(n for n in grid.get_node_ids() if self.node_partition.get(n) in last)
        return self._messages(nodes, arrays, MessageType.EVALUATE, server_round)

    def aggregate_evaluate(self, server_round: int, replies) -> MetricRecord | None:
        acked = sorted(int(m.content["metrics"]["partition-id"]) for m in replies if not m.has_error())
        if self.history:
            self.history[-1]["final_broadcast_received_by"] = acked
        return None

    def summary(self) -> None:
        s = self.settings
        log(INFO, "fedmap strategy: %s, %d round(s), uplink %s, downlink %s, %d rovers (min %d), deadline %g s",
            s.federation.aggregator, s.federation.rounds, self.up_spec.label(), self.down_spec.label(), s.rovers,
            s.min_rovers, s.deadline)

    # -- per round, on the base ---------------------------------------------------------------

    def checkpoint(self, server_round: int, arrays: ArrayRecord) -> MetricRecord | None:
        """``evaluate_fn`` hook: save the global model after every round, atomically."""
        if server_round == 0 or self.held is None:
            return None
        model = build_model(preset(self.settings.net, self.shape[0]))
        set_weights(model, self.held)
        save_model(model, run_dir(self.settings.out) / f"global_model_round{server_round}.safetensors",
                   extra={"round": server_round})
        write_status(self.settings.out, "running", round=server_round, saved=True)
        return None

    def result(self) -> FederationResult:
        return FederationResult(self.held, self.history, {"name": self.settings.federation.aggregator,
                                                          **self.aggregator.hyperparameters()})


def run_base_station(grid: Grid, settings: RunSettings) -> Path:
    """R rounds on ``grid``, then render, refine, evaluate and write the outputs."""
    t0 = time.perf_counter()
    strategy = FedmapStrategy(settings)
    strategy.start(grid=grid, initial_arrays=to_record(b""), num_rounds=settings.federation.rounds,
                   timeout=settings.deadline, evaluate_fn=strategy.checkpoint)
    return write_base_outputs(strategy, settings, federation_s=time.perf_counter() - t0)


def write_base_outputs(strategy: FedmapStrategy, settings: RunSettings, *, federation_s: float) -> Path:
    """The demo's output folder (plus per-round checkpoints and the byte ledger)."""
    from fedmap.maps.grid import GridMap
    from fedmap.pipeline import global_map
    from fedmap.refine import RefineConfig

    fed = strategy.result()
    h, w = strategy.shape
    t = time.perf_counter()
    model, rgb, classes, refined = global_map(preset(settings.net, h), fed.weights, (h, w),
                                              RefineConfig(min_size=settings.min_size))
    truth = load_truth(settings)
    flower = {
        "settings": {k: v for k, v in vars(settings).items() if k != "federation"} | {"out": str(settings.out)},
        "missing": {r["round"]: r["missing"] for r in fed.history},
        "flower_bytes": [{"round": r["round"], "uplink": r["flower_uplink_bytes"],
                          "downlink": r["flower_downlink_bytes"]} for r in fed.history],
    }
    metrics = {"aggregator": fed.aggregator, "bytes": fed.total_bytes(), "ledger": fed.ledger(),
               "rounds": fed.history, "flower": flower}
    out = settings.out
    if truth is not None:
        from fedmap.pipeline import PipelineConfig, PipelineResult, evaluate, truth_summary, write_outputs

        if truth.shape != (h, w):
            raise FedmapError(f"the ground truth is {truth.shape}, the rovers' maps are {(h, w)}")
        pc = PipelineConfig(terrain=settings.terrain or "mars", size=max(64, h), agents=settings.rovers,
                            net=settings.net, init=settings.init, central=False, federation=settings.federation,
                            refine=RefineConfig(min_size=settings.min_size), eval_pairs=settings.pairs,
                            seed=settings.federation.seed)
        metrics = {"global": evaluate(truth, classes, pc), "refined": evaluate(truth, refined, pc), "agents": [],
                   "truth": truth_summary(truth), **metrics}
        timings = {"federation_s": federation_s, "evaluate_s": time.perf_counter() - t}
        write_outputs(PipelineResult(pc, truth, [], model, rgb, classes, refined, fed, metrics, timings), out)
    else:
        from fedmap.maps.io import save_map
        from fedmap.report import AtomicDir, to_json

        frame = GridMap(classes, 1.0, "federated global map")
        with AtomicDir(out) as tmp:
            (tmp / "metrics.json").write_text(to_json({**metrics, "timings": {"federation_s": federation_s}}))
            save_model(model, tmp / "global_model.safetensors", extra={"flower": flower["settings"]})
            save_map(frame, tmp / "global_map.png")
            save_map(frame.with_classes(refined, "refined global map"), tmp / "refined_map.png")
    for ckpt in sorted(run_dir(out).glob("global_model_round*.safetensors")):
        os.replace(ckpt, out / ckpt.name)  # same filesystem: each move is atomic
    write_status(out, "done", rounds=len(fed.history), out=str(out))
    return out


@app.main()
def main(grid: Grid, context: Context) -> None:
    settings = RunSettings.from_run_config(dict(context.run_config))
    try:
        out = run_base_station(grid, settings)
    except Exception as e:  # the base-station command waits on this file: never leave it "running"
        msg = str(e) if isinstance(e, FedmapError) else f"{type(e).__name__}: {e}".splitlines()[0]
        write_status(settings.out, "failed", message=msg)
        log(INFO, "fedmap: error: %s", msg)
        raise
    log(INFO, "fedmap: outputs in %s", out)
