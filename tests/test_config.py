"""Run configs: TOML + overrides -> PipelineConfig, typos and types named, TOML written back."""

from __future__ import annotations

import tomllib

import pytest

from fedmap.config import (
    dumps_toml,
    load_preset,
    method_config,
    overrides_from,
    parse_set,
    preset_names,
    resolve,
    terrain_source,
    to_pipeline_config,
)
from fedmap.errors import FedmapError
from fedmap.federation.runner import FederationConfig
from fedmap.nets.init import ModelConfig
from fedmap.nets.training import TrainConfig
from fedmap.pipeline import PipelineConfig


def write(tmp_path, text, name="run.toml"):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_paper_preset_is_the_papers_setup():
    """The paper's stated settings (DESIGN.md section 3), built by hand through the config classes."""
    cfg = method_config("paper")
    ref = PipelineConfig(model=ModelConfig(net="paper", init="meta"), federation=FederationConfig(
        rounds=1, aggregator="fedavg", uplink="fp32", downlink="fp32"), train=TrainConfig(epochs=100, lr=1e-3, masked=False))
    assert cfg == ref


def test_fedmap_preset_is_grids_coverage_and_update_payloads():
    cfg = method_config("fedmap")
    ref = PipelineConfig(method="fedmap", model=ModelConfig(net="grid", init="random"), federation=FederationConfig(
        aggregator="coverage", uplink="update-int4+zstd", downlink="update-int8+zstd"),
        train=TrainConfig(epochs=100, lr=0.05, masked=True))
    assert cfg == ref


def test_presets_are_shipped_data_and_validated():
    assert preset_names() == ("fedmap", "paper")
    assert load_preset("paper")["model"] == {"net": "paper", "init": "meta"}
    with pytest.raises(FedmapError, match="unknown method 'papr'; choose one of fedmap, paper"):
        method_config("papr")


def test_method_config_keywords_are_the_run_config():
    """Python keywords and TOML sections are one path: the same settings give the same config."""
    cfg = method_config("paper", rounds=3, epochs=7, eta=0.003, aggregator="fedadam", pairs=20, seed=5, size=64)
    r = resolve(overrides=[{"seed": 5, "terrain": {"size": 64}, "train": {"epochs": 7}, "evaluate": {"pairs": 20},
                            "federation": {"rounds": 3, "eta": 0.003, "aggregator": "fedadam"}}])
    assert cfg == to_pipeline_config(r)
    assert cfg.federation.seed == 5 and cfg.model.init == "meta"
    assert cfg.federation.local == cfg.train  # [train] is the federation's local training, one source
    with pytest.raises(FedmapError, match="unknown setting 'epoch' \\(did you mean 'epochs'\\?\\)"):
        overrides_from({"epoch": 3})


def test_file_then_options_override(tmp_path):
    path = write(tmp_path, """
method = "fedmap"
seed = 4
[train]
lr = 0.02
epochs = 30
[federation]
aggregator = "fedyogi"
eta = 0.003
[explore]
agents = 6
mode = "grid"
""")
    r = resolve(path, [{"train": {"epochs": 7}}, {"explore": {"agents": 9}}])
    cfg = to_pipeline_config(r)
    assert cfg.model.net == "grid"                    # from the fedmap preset
    assert cfg.train.lr == 0.02                       # file beats preset (0.05)
    assert cfg.train.masked is True                   # preset kept where the file is silent
    assert cfg.train.epochs == 7                      # option beats file
    assert cfg.explore.agents == 9 and cfg.explore.mode == "grid"
    assert cfg.federation.aggregator == "fedyogi" and cfg.federation.eta == 0.003
    assert cfg.seed == 4 and cfg.federation.seed == 4
    # an option's method changes the preset under the file's explicit values
    r2 = resolve(path, [{"method": "paper"}])
    assert r2["model"]["net"] == "paper" and r2["train"]["lr"] == 0.02


@pytest.mark.parametrize("text,message", [
    ("[explore]\nagnets = 3\n", "unknown key 'agnets' in [explore] of run.toml (did you mean 'agents'?)"),
    ("[explor]\nagents = 3\n", "unknown key 'explor' in run.toml (did you mean 'explore'?)"),
    ("sed = 1\n", "unknown key 'sed' in run.toml (did you mean 'seed'?)"),
    ("[train]\nepochs = \"100\"\n", "[train] epochs in run.toml must be an integer, got '100'"),
    ("[train]\nepochs = true\n", "[train] epochs in run.toml must be an integer, got True"),
    ("[train]\nlr = \"fast\"\n", "[train] lr in run.toml must be an integer or a number, got 'fast'"),
    ("[train]\nmasked = 1\n", "[train] masked in run.toml must be true or false, got 1"),
    ("[terrain.options]\npixel_sise = 2.0\n", "unknown key 'pixel_sise' in [terrain.options] of run.toml "
                                              "(did you mean 'pixel_size'?)"),
    ("explore = 3\n", "[explore] in run.toml must be a table"),
    ("[train\nepochs = 1\n", "cannot read config"),
    ("[train]\nlr = nan\n", "[train] lr in run.toml must be a finite number, got nan"),
])
def test_config_mistakes_are_named(tmp_path, text, message):
    path = write(tmp_path, text)
    with pytest.raises(FedmapError) as exc:
        resolve(path)
    assert message in str(exc.value)
    assert "\n" not in str(exc.value)


def test_values_are_checked_by_the_library_classes(tmp_path):
    with pytest.raises(FedmapError, match="rounds must be >= 1"):
        to_pipeline_config(resolve(write(tmp_path, "[federation]\nrounds = 0\n")))
    with pytest.raises(FedmapError, match="unknown aggregator|aggregator"):
        to_pipeline_config(resolve(write(tmp_path, "[federation]\naggregator = \"fedmean\"\n")))
    with pytest.raises(FedmapError, match="max_slope_deg"):
        terrain_source(resolve(write(tmp_path, "[thresholds]\nmax_slope_deg = 95\n")))
    with pytest.raises(FedmapError, match="unknown terrain source kind 'file'"):
        terrain_source(resolve(write(tmp_path, "[terrain]\nkind = \"file\"\npath = \"x\"\n")))
    with pytest.raises(FedmapError, match="no such config file"):
        resolve(tmp_path / "missing.toml")


def test_relative_terrain_path_is_relative_to_the_file(tmp_path):
    (tmp_path / "cfg").mkdir()
    path = write(tmp_path / "cfg", "[terrain]\nkind = \"dem\"\npath = \"../dems/a.tif\"\nsize = 64\n")
    r = resolve(path)
    assert r["terrain"]["path"] == str((tmp_path / "dems" / "a.tif").resolve())


def test_terrain_replacement_keeps_grid_keys(tmp_path):
    path = write(tmp_path, "[terrain]\nkind = \"tiles\"\npath = \"t\"\nlon = 1\nlat = 2\nsize = 96\ncrop = 500\n"
                           "[terrain.options]\noffset = 0.0\n")
    r = resolve(path, terrain={"kind": "dem", "path": "/x.tif"})
    assert r["terrain"] == {"kind": "dem", "path": "/x.tif", "size": 96, "crop": 500}


def test_written_toml_reads_back_identically(tmp_path):
    path = write(tmp_path, "[terrain]\nkind = \"dem\"\npath = \"a \\\"b\\\".tif\"\ncrop = [1, 65, 2, 66]\n"
                           "[terrain.options]\nshape = [10, 20]\nbyteorder = \"little\"\n")
    r = resolve(path, [{"train": {"lr": 1e-7}}])
    text = dumps_toml(r)
    assert tomllib.loads(text) == r
    back = write(tmp_path, text, "back.toml")
    assert resolve(back) == r  # the resolved config is a valid config that resolves to itself


def test_a_toml_file_with_a_byte_order_mark_reads_as_without(tmp_path):
    text = "[train]\nlr = 0.01\n"
    plain = write(tmp_path, text, "plain.toml")
    marked = tmp_path / "marked.toml"
    marked.write_bytes(b"\xef\xbb\xbf" + text.encode())  # as Windows' Notepad saves UTF-8
    assert resolve(marked) == resolve(plain)
    assert resolve(marked)["train"]["lr"] == 0.01


def test_parse_set():
    assert parse_set("train.lr=0.01") == {"train": {"lr": 0.01}}
    assert parse_set("federation.uplink = fp16") == {"federation": {"uplink": "fp16"}}
    assert parse_set("terrain.crop=[0, 64, 0, 64]") == {"terrain": {"crop": [0, 64, 0, 64]}}
    assert parse_set("seed=3") == {"seed": 3}
    with pytest.raises(FedmapError, match="section.key=value"):
        parse_set("train.lr")
    with pytest.raises(FedmapError, match="unknown key 'lrr' in \\[train\\] of the command-line options"):
        resolve(overrides=[parse_set("train.lrr=1")])


def test_the_presets_init_goes_with_its_network(tmp_path):
    """paper's meta-init is for the paper network: swapping the network without an init
    starts from random weights; an explicit init, or a weights file, is kept."""
    assert method_config("paper").model.init == "meta"
    assert method_config("paper", net="small").model.init == "random"
    assert method_config("paper", net="grid").model.init == "random"  # (meta would be refused for grid)
    assert method_config("paper", net="small", init="empty").model.init == "empty"
    assert method_config("paper", net="small", init_weights="w.safetensors").model.init == "meta"
    path = write(tmp_path, '[model]\nnet = "small"\ninit = "meta"\n')
    assert to_pipeline_config(resolve(path)).model.init == "meta"  # said in the file: kept
    with pytest.raises(FedmapError, match="crop does not apply to built-in terrain"):
        method_config("paper", crop=64)


def test_a_weights_file_without_an_init_is_a_meta_init():
    """The same rule for every command: --init-weights alone means init meta from that file."""
    r = resolve(overrides=[{"method": "fedmap", "model": {"net": "paper", "init_weights": "w.safetensors"}}])
    assert r["model"]["init"] == "meta"
    r = resolve(overrides=[{"model": {"init_weights": "w.safetensors", "init": "empty"}}])
    assert r["model"]["init"] == "empty"  # an explicit init wins (PipelineConfig then refuses the pair)
