"""End-to-end CLI tests on tiny grids, and the bad-input contract (one line, exit 2, nothing written)."""

import json

import numpy as np
import pytest

import fedmap.pipeline as pipeline_mod
from fedmap._util import OUTPUT_MARKER
from fedmap.cli import main
from fedmap.errors import FedmapError
from fedmap.maps.grid import GridMap, classes_from_rgb
from fedmap.maps.io import load_map, save_map
from fedmap.nets.model import load_model, render

TINY = ["demo", "--method", "paper", "--size", "64", "--local-epochs", "2", "--pairs", "5"]


def _run(args, capsys):
    rc = main(args)
    out = capsys.readouterr()
    return rc, out.out, out.err


def test_demo_end_to_end_tiny(tmp_path, capsys):
    out = tmp_path / "run"
    rc, stdout, err = _run(TINY + ["-o", str(out)], capsys)
    assert rc == 0, err
    assert "wall time" in stdout
    metrics = json.loads((out / "metrics.json").read_text())
    for key in ("global", "refined", "agents", "bytes", "rounds"):
        assert key in metrics
    assert len(metrics["agents"]) == 4
    assert 0 <= metrics["global"]["path"]["f1"] <= 1
    # the stored model alone re-renders exactly the stored global map
    model = load_model(out / "global_model.safetensors")
    classes = classes_from_rgb(render(model, 64, 64))
    np.testing.assert_array_equal(classes, load_map(out / "global_map.png").classes)
    # byte ledger: 4 rovers x 1 round, fp32 payload of the paper network (~4 B/param)
    up = metrics["rounds"][0]["uplink_bytes"]
    assert len(up) == 4 and all(4 * 199_683 < v < 4 * 199_683 + 4096 for v in up.values())
    assert (out / "figure.png").stat().st_size > 10_000
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temp folders left


def test_demo_is_reproducible(tmp_path, capsys):
    a, b = tmp_path / "a", tmp_path / "b"
    assert _run(TINY + ["--seed", "3", "-o", str(a)], capsys)[0] == 0
    assert _run(TINY + ["--seed", "3", "-o", str(b)], capsys)[0] == 0
    ma, mb = (json.loads((p / "metrics.json").read_text()) for p in (a, b))
    ma.pop("timings"), mb.pop("timings")
    for r in ma["rounds"] + mb["rounds"]:
        r.pop("seconds")
    assert ma == mb
    assert (a / "global_model.safetensors").read_bytes() == (b / "global_model.safetensors").read_bytes()


@pytest.mark.parametrize(
    "args, message",
    [
        (["demo", "--aggregator", "fedfoo"], "unknown aggregator"),
        (["demo", "--size", "0"], "size must be"),
        (["demo", "--size", "abc"], "not a valid integer"),
        (["demo", "--explore", "spiral"], "unknown exploration mode"),
        (["demo", "--agents", "3"], "exactly 4 agents"),
        (["demo", "--terrain", "venus"], "unknown terrain"),
        (["demo", "--rounds", "0"], "rounds must be"),
        (["demo", "--no-such-option"], "No such option"),
    ],
)
def test_bad_demo_options(tmp_path, capsys, args, message):
    out = tmp_path / "out"
    rc, _, err = _run(args + ["-o", str(out)], capsys)
    assert rc == 2
    assert err.startswith("error: ") and message in err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert not out.exists()


def test_bad_map_files(tmp_path, capsys):
    good = tmp_path / "good.png"
    save_map(GridMap(np.zeros((16, 16), np.uint8)), good)
    other = tmp_path / "other.png"
    save_map(GridMap(np.zeros((8, 8), np.uint8)), other)
    corrupt = tmp_path / "corrupt.png"
    corrupt.write_bytes(b"\x89PNG\r\n\x1a\n" + b"\x00" * 20)
    cases = [
        ([str(tmp_path / "missing.png"), str(good)], "no such file"),
        ([str(corrupt), str(good)], "corrupt.png"),
        ([str(other), str(good)], "8x8"),
    ]
    for args, message in cases:
        rc, _, err = _run(["evaluate", *args], capsys)
        assert rc == 2 and message in err and err.count("\n") == 1, err


def test_failed_run_keeps_previous_results(tmp_path, capsys, monkeypatch):
    out = tmp_path / "run"
    out.mkdir()
    (out / "metrics.json").write_text('{"previous": true}')
    (out / OUTPUT_MARKER).write_text("")  # an earlier run's folder

    def boom(*a, **k):
        raise FedmapError("simulated failure while rendering")

    monkeypatch.setattr(pipeline_mod, "render", boom)
    rc, _, err = _run(TINY + ["-o", str(out)], capsys)
    assert rc == 2 and "simulated failure" in err
    assert json.loads((out / "metrics.json").read_text()) == {"previous": True}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]


def test_bandwidth_report_tiny(tmp_path, capsys, monkeypatch):
    import fedmap.experiments.table3 as br

    # shrink the federated runs to 1-2 local epochs so the test stays fast
    tiny = {label: (method, rounds, 2, overrides)
            for label, (method, rounds, _, overrides) in list(br.FEDERATED_RUNS.items())[::2]}
    monkeypatch.setattr(br, "FEDERATED_RUNS", tiny)
    out = tmp_path / "bw"
    rc, stdout, err = _run(["bandwidth", "--size", "64", "--pairs", "5", "-o", str(out)], capsys)
    assert rc == 0, err
    res = json.loads((out / "bandwidth.json").read_text())
    fp16 = next(r for r in res["model_payloads"] if r["codec"] == "fp16")
    assert 399_366 < fp16["bytes"] < 399_366 + 512  # the paper's arithmetic plus a small header
    assert {r["codec"] for r in res["image_codecs"]} >= {"png-palette", "zstd-2bit", "jpeg q26"}
    lossless = [r for r in res["image_codecs"] if r["lossless"]]
    assert lossless and all(r["psnr"] is None and r["f1"] == 1.0 for r in lossless)  # inf -> null in JSON
    fed = res["federated"]
    assert len(fed) == 2
    # a run's uplink total is rounds x rovers x per-rover-per-round bytes
    for p in fed:
        assert p["bytes"] == pytest.approx(p["rounds"] * 4 * p["uplink_per_agent_round"])
    assert (out / "rd.png").stat().st_size > 10_000 and "Table III" in (out / "report.md").read_text()
