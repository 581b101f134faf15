"""Training precision: fp32 is today's arithmetic bit for bit, bf16 computes the same function
within bf16 rounding, ``auto`` follows the CPU, and the precision is recorded."""

import json
import os
import platform
import subprocess
import sys

import numpy as np
import pytest
import torch

from fedmap.cli import main
from fedmap.cli import run as run_cli
from fedmap.config import method_config
from fedmap.errors import FedmapError
from fedmap.evaluation.metrics import psnr
from fedmap.maps.grid import GridMap
from fedmap.nets import training
from fedmap.nets.model import build_model, get_weights, grid_coords, render
from fedmap.nets.training import PRECISIONS, TrainConfig, fit, native_bf16, precision_reason, resolve_precision


def _reference_fp32_fit(model, grid: GridMap, epochs: int, lr: float) -> list[float]:
    """The full-grid Adam/MSE loop written out by hand in fp32 (the paper's setup)."""
    feats = model.features(grid_coords(*grid.shape)).detach()
    target = torch.from_numpy(grid.to_rgb().reshape(-1, 3))
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    losses = []
    for _ in range(epochs):
        opt.zero_grad(set_to_none=True)
        loss = ((torch.sigmoid(model.mlp(feats)) - target) ** 2).mean(dim=1).sum() / target.shape[0]
        loss.backward()
        opt.step()
        losses.append(loss.item())
    return losses


def test_fp32_is_the_plain_fp32_loop_bit_for_bit(tiny_net, blob_map):
    a, b = build_model(tiny_net, seed=1), build_model(tiny_net, seed=1)
    la = fit(a, blob_map, TrainConfig(epochs=6, lr=1e-2, precision="fp32"))
    lb = _reference_fp32_fit(b, blob_map, 6, 1e-2)
    assert la == lb
    for k, v in get_weights(a).items():
        np.testing.assert_array_equal(v, get_weights(b)[k])


def test_bf16_is_the_same_function_within_rounding(blob_map):
    torch.manual_seed(0)
    models = {p: build_model(seed=2) for p in ("fp32", "bf16")}  # the paper network
    curves = {p: fit(m, blob_map, TrainConfig(epochs=30, lr=1e-3, precision=p)) for p, m in models.items()}
    # bf16 really changes the arithmetic (otherwise this test would prove nothing) ...
    assert curves["bf16"] != curves["fp32"]
    # ... but not the result: the loss curves and the rendered maps agree within bf16 rounding
    np.testing.assert_allclose(curves["bf16"], curves["fp32"], rtol=0.05, atol=2e-3)
    truth = blob_map.to_rgb()
    q = {p: psnr(truth, render(m, *blob_map.shape)) for p, m in models.items()}
    assert abs(q["bf16"] - q["fp32"]) < 0.3, q


@pytest.mark.parametrize("precision", ["fp32", "bf16"])
def test_same_seed_same_bytes(tiny_net, blob_map, precision):
    runs = []
    for _ in range(2):
        m = build_model(tiny_net, seed=5)
        fit(m, blob_map, TrainConfig(epochs=4, lr=1e-2, batch=200, precision=precision), seed=9)
        runs.append(b"".join(v.tobytes() for v in get_weights(m).values()))
    assert runs[0] == runs[1]


def test_auto_follows_the_cpu_and_unknown_names_are_refused():
    expected = "bf16" if (torch.cpu._is_avx512_bf16_supported() or torch.cpu._is_amx_tile_supported()) else "fp32"
    assert native_bf16() == (expected == "bf16")
    assert resolve_precision("auto") == expected == TrainConfig().precision
    assert TrainConfig(precision="fp32").precision == "fp32"
    with pytest.raises(FedmapError, match="unknown precision 'fp16'"):
        TrainConfig(precision="fp16")


def test_the_config_records_the_resolved_precision(tmp_path):
    assert method_config("paper", precision="fp32").federation.local.precision == "fp32"
    assert method_config("paper").federation.local.precision == resolve_precision("auto")
    d = method_config("paper", precision="bf16").to_dict()
    assert json.loads(json.dumps(d))["federation"]["local"]["precision"] == "bf16"
    with pytest.raises(FedmapError, match="unknown precision"):
        method_config("paper", precision="half")


@pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc", reason="glibc only")
def test_allocator_setting_is_applied_once_and_can_be_turned_off():
    code = ("from fedmap.nets.training import keep_freed_memory as k; import ctypes, sys; "
            "sys.stdout.write(str(k()))")
    on = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                        env={**os.environ, "FEDMAP_MALLOC_TUNING": "1"}).stdout
    off = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env={**os.environ, "FEDMAP_MALLOC_TUNING": "0"}).stdout
    assert (on, off) == ("True", "False")


#: In a fresh process with fedmap's allocator setting: a 400 MB tensor freed under a small block
#: allocated after it (so the heap cannot shrink from its top); resident MB before and after
#: ``release_freed_memory``.
_TRIM = """
import sys, torch
from fedmap.nets.training import keep_freed_memory, release_freed_memory
def rss():
    return int(open("/proc/self/statm").read().split()[1]) * 4096 / 2**20
assert keep_freed_memory()
big = torch.ones(100 * 2**20)  # 400 MB, on the heap (mmap is off)
small = torch.ones(1024)  # above it
del big
before = rss()
released = release_freed_memory()
sys.stdout.write(f"{before:.0f} {rss():.0f} {released}")
"""


@pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc", reason="glibc only")
def test_freed_memory_kept_on_the_heap_is_released_between_stages():
    """The allocator setting keeps a freed 400 MB block resident (the heap shrinks only from its
    top); ``release_freed_memory`` gives its pages back, so a run's peak is its largest stage's."""
    before, after, released = subprocess.run([sys.executable, "-c", _TRIM], capture_output=True, text=True,
                                             check=True).stdout.split()
    assert released == "True" and float(before) - float(after) > 300, (before, after)


@pytest.mark.parametrize("native", [True, False])
def test_the_precision_reason_follows_the_cpu(monkeypatch, native):
    """The words agree with what runs: :func:`resolve_precision` under the same detection."""
    monkeypatch.setattr(training, "native_bf16", lambda: native)
    auto = precision_reason("auto")
    assert auto.startswith(f"{resolve_precision('auto')} (auto): ")
    if native:
        assert auto == "bf16 (auto): this CPU multiplies bfloat16 natively (AVX-512 BF16 or AMX)"
        assert precision_reason("fp32").endswith("; auto would train in bf16")
    else:
        assert auto == ("fp32 (auto): this CPU has no native bf16 (no AVX-512 BF16 or AMX); bf16 would be emulated "
                        "and slower")
        assert precision_reason("bf16").endswith(", so bf16 is emulated and slower than fp32")
    assert precision_reason("bf16").startswith("bf16, as asked; ")
    assert precision_reason("fp32").startswith("fp32, as asked; ")
    for name in PRECISIONS:  # feature grids train in fp32 whatever was asked
        assert precision_reason(name, grid=True).startswith("fp32: feature grids always train in fp32")


_TINY_DEMO = ["demo", "--method", "paper", "--size", "64", "--local-epochs", "1", "--pairs", "2", "--rounds", "1"]


@pytest.mark.parametrize("native", [True, False])
def test_the_demo_says_which_precision_it_trains_in_before_training(monkeypatch, capsys, tmp_path, native):
    """The line comes before the training (which is stopped here, to keep the test fast)."""
    monkeypatch.setattr(training, "native_bf16", lambda: native)

    def stop(config, **kwargs):
        raise FedmapError(f"stopped before training in {config.train.precision}")

    monkeypatch.setattr(run_cli, "run_pipeline", stop)
    assert main([*_TINY_DEMO, "-o", str(tmp_path / "d")]) == 2
    out = capsys.readouterr()
    used = "bf16" if native else "fp32"
    assert f"training precision: {precision_reason('auto')}" in out.out.splitlines()
    assert f"training precision: {used} (auto): " in out.out and f"stopped before training in {used}" in out.err
    # two methods side by side: one line each, the feature grids' in fp32
    assert main(["demo", "--size", "64", "-o", str(tmp_path / "d2")]) == 2
    lines = [line for line in capsys.readouterr().out.splitlines() if line.startswith("training precision")]
    assert lines == [f"training precision (paper): {precision_reason('auto')}"]  # stopped in paper's run


def test_the_demo_trains_in_the_precision_its_line_names(monkeypatch, capsys, tmp_path):
    """A CPU without native bf16 (as detected): the line says fp32 and why, and fp32 ran."""
    monkeypatch.setattr(training, "native_bf16", lambda: False)
    assert main([*_TINY_DEMO, "-o", str(tmp_path / "d")]) == 0
    out = capsys.readouterr().out
    assert ("training precision: fp32 (auto): this CPU has no native bf16 (no AVX-512 BF16 or AMX); bf16 would be "
            "emulated and slower") in out.splitlines()
    ran = json.loads((tmp_path / "d" / "config.json").read_text())
    assert ran["train"]["precision"] == ran["federation"]["local"]["precision"] == "fp32"


def test_torch_openmp_threads_spin_briefly_unless_the_user_chose():
    """Beside busy processes, OpenMP threads spinning at barriers (libgomp's default 300,000
    spins) made the demo 4.9x slower, not the 2x a fair share predicts: importing fedmap sets
    a short spin for the OpenMP runtime torch loads, and keeps a value the user set."""
    import fedmap

    code = ("import fedmap, torch, os; torch.ones(64, 64) @ torch.ones(64, 64); "
            "print(os.environ['GOMP_SPINCOUNT'], any('libgomp' in line for line in open('/proc/self/maps')))")
    env = {k: v for k, v in os.environ.items() if k != "GOMP_SPINCOUNT"}
    got = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert got.stdout.split() == [fedmap.GOMP_SPINCOUNT, "True"]  # set, and read by the runtime torch loaded
    mine = subprocess.run([sys.executable, "-c", code], env={**env, "GOMP_SPINCOUNT": "123"}, capture_output=True,
                          text=True, check=True)
    assert mine.stdout.split() == ["123", "True"]
