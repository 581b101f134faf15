"""User mistakes found by a review of the commands' bad-input paths: each is one line with exit
status 2, before any expensive work, and nothing that was there is lost."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import torch

from fedmap.cli import main
from fedmap.errors import FedmapError
from fedmap.maps.grid import GridMap
from fedmap.maps.io import load_map, save_map
from fedmap.maps.sources import TerrainSource, load_truth
from fedmap.nets.predictor import MapPredictor, PredictorConfig, PredictorTraining, load_predictor, save_predictor


def _one_line_error(capsys, *args) -> str:
    rc = main([*map(str, args)])
    err = capsys.readouterr().err
    assert rc == 2 and err.startswith("error: ") and len(err.strip().splitlines()) == 1, (args, rc, err)
    return err


@pytest.mark.parametrize("command", [["evaluate", "a.png", "b.png"], ["ablate-init"], ["meta-coder"],
                                     ["meta-predictor"], ["federate-predictor", "a.png"], ["bandwidth"],
                                     ["reproduce"]])
def test_a_negative_seed_is_refused_by_every_command(command, capsys):
    err = _one_line_error(capsys, *command, "--seed", "-1")
    assert "--seed" in err and "-1" in err


def test_a_diverged_predictor_is_never_written_and_a_bad_schedule_is_refused_first(tmp_path, capsys):
    model = MapPredictor(PredictorConfig(stem=4, width=8, dilations=(1, 2)))
    good = save_predictor(model, tmp_path / "p.safetensors").read_bytes()
    with torch.no_grad():
        next(model.parameters()).view(-1)[0] = float("nan")
    with pytest.raises(FedmapError, match=r"1 of [\d,]+ predictor weights are NaN or infinite") as e:
        save_predictor(model, tmp_path / "p.safetensors")
    assert "\n" not in str(e.value)
    assert (tmp_path / "p.safetensors").read_bytes() == good  # the earlier file is whole
    assert load_predictor(tmp_path / "p.safetensors") is not None
    for lr in (float("inf"), float("nan"), 0.0):
        with pytest.raises(FedmapError, match="lr must be finite and > 0"):
            PredictorTraining(lr=lr)
    for every, steps in (("0", "5"), ("50", "2")):
        err = _one_line_error(capsys, "meta-predictor", "--every", every, "--steps", steps, "--per-category", "1",
                              "-o", tmp_path / "p.safetensors")
        assert "--every must be in [1, --steps]" in err
    assert (tmp_path / "p.safetensors").read_bytes() == good


def test_certs_keep_an_existing_ca_unless_forced_and_refuse_bad_arguments(tmp_path, capsys):
    folder = tmp_path / "c"
    assert main(["certs", str(folder), "--rovers", "1"]) == 0
    capsys.readouterr()
    before = {p.name: p.read_bytes() for p in folder.iterdir()}
    err = _one_line_error(capsys, "certs", folder, "--rovers", "1")
    assert "already holds a CA" in err and "--force" in err
    assert {p.name: p.read_bytes() for p in folder.iterdir()} == before
    assert main(["certs", str(folder), "--rovers", "1", "--force"]) == 0
    capsys.readouterr()
    assert (folder / "ca.crt").read_bytes() != before["ca.crt"]
    (tmp_path / "afile").write_text("x")
    for args, expect in ((["--days", "-5"], "days must be in [1, 36500]"), (["--days", "99999999"], "days must be"),
                         (["--host", ""], "is not a host name"), (["--host", "bad host!"], "is not a host name")):
        assert expect in _one_line_error(capsys, "certs", tmp_path / "new", *args)
    assert "is not a folder" in _one_line_error(capsys, "certs", tmp_path / "afile")
    assert "cannot write certificates to /proc/c" in _one_line_error(capsys, "certs", "/proc/c")
    assert not (tmp_path / "new").exists()


def test_merge_takes_pixel_size_only_for_maps_that_store_none(tmp_path, capsys):
    classes = load_truth(TerrainSource(size=128), seed=3).classes[:100, :100]
    save_map(GridMap(classes, 1.0, "a"), tmp_path / "a.tif")
    np.save(tmp_path / "b.npy", classes)
    err = _one_line_error(capsys, "merge", tmp_path / "a.tif", tmp_path / "b.npy", "--pixel-size", "3",
                          "-o", tmp_path / "m.tif")
    assert "stores 1 m cells but --pixel-size says 3" in err and not (tmp_path / "m.tif").exists()
    assert main(["merge", str(tmp_path / "a.tif"), str(tmp_path / "b.npy"), "--pixel-size", "1",
                 "-o", str(tmp_path / "m.tif")]) == 0
    assert load_map(tmp_path / "m.tif").pixel_size == 1.0


def test_a_quoted_tilde_is_the_home_folder_for_every_path(tmp_path, monkeypatch, capsys):
    """``-o "~/m.png"`` (quoted: the shell left the ``~``) is the home folder's, for the maps read
    and the file written alike: merge wrote a folder named ``~`` where mission read the home folder."""
    home, work = tmp_path / "home", tmp_path / "work"
    home.mkdir()
    work.mkdir()
    monkeypatch.setenv("HOME", str(home))
    monkeypatch.chdir(work)
    classes = load_truth(TerrainSource(size=128), seed=3).classes[:100, :100]
    save_map(GridMap(classes, 1.0, "a"), home / "a.png")
    assert main(["merge", "~/a.png", "~/a.png", "-o", "~/m.png"]) == 0
    assert np.array_equal(load_map(home / "m.png").classes, classes)
    assert not (work / "~").exists()
    assert str(home / "m.png") in capsys.readouterr().out


def test_the_installed_command_gives_these_errors_without_a_traceback(tmp_path):
    r = subprocess.run([sys.executable, "-m", "fedmap", "certs", "/proc/c"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and r.stderr.startswith("error: cannot write certificates") and "Traceback" not in r.stderr


def test_more_mistakes_are_one_line_before_the_work(tmp_path, capsys, monkeypatch):
    import fedmap.cli.meta as cli_meta
    import fedmap.cli.mission as cli_mission

    calls = []
    monkeypatch.setattr(cli_meta, "learn_coder_prior", lambda *a, **k: calls.append("missions"))
    monkeypatch.setattr(cli_mission, "mission_terrain", lambda *a, **k: calls.append("terrain"))
    assert "cannot write /proc/mc.bin" in _one_line_error(capsys, "meta-coder", "-o", "/proc/mc.bin")
    assert "at least 16x16" in _one_line_error(capsys, "ablate-init", "--size", "10")
    assert "unknown collection layout 'kiti'" in _one_line_error(capsys, "ablate-init", "--layout", "kiti")
    assert "is for a collection folder" in _one_line_error(capsys, "meta-coder", "--layout", "dem")
    for flag in (["--resume"], ["--listen", "0.0.0.0:9092"], ["--insecure"]):
        err = _one_line_error(capsys, "mission", *flag, "-o", tmp_path / "m")
        assert flag[0] in err and "add --deploy" in err
    assert "--pairs" in _one_line_error(capsys, "evaluate", "a.png", "b.png", "--pairs", "99999999999")
    err = _one_line_error(capsys, "mision")
    assert err.count("Did you mean") == 1 and "'mission'" in err
    assert not calls


def test_export_into_a_file_or_an_unwritable_place_is_one_line(tmp_path, capsys):
    out = tmp_path / "m"
    assert main(["mission", "--size", "64", "--steps", "8", "--sync-every", "4", "--rovers", "2",
                 "--strategies", "raw", "--no-animation", "-o", str(out)]) == 0
    capsys.readouterr()
    (tmp_path / "afile").write_text("keep")
    err = _one_line_error(capsys, "export", out, "-f", "npy", "-o", tmp_path / "afile")
    assert "it exists and is not a folder" in err and (tmp_path / "afile").read_text() == "keep"
    assert "cannot write to /proc/e" in _one_line_error(capsys, "export", out, "-f", "npy", "-o", "/proc/e")
    assert main(["export", str(out), "-f", "npy", "-o", str(tmp_path / "e")]) == 0
    assert (tmp_path / "e" / "raw_global.npy").is_file()


def test_federate_predictor_checks_its_arguments_before_the_sites_missions(tmp_path, capsys, monkeypatch):
    import fedmap.cli.predictorfed as cli_pf

    ran = []
    monkeypatch.setattr(cli_pf, "site_maps", lambda *a, **k: ran.append(1))
    files = []
    for name in ("a", "b"):
        f = tmp_path / f"mission_{name}.toml"
        f.write_text('seed = 0\n[terrain]\nkind = "builtin"\nterrain = "mars"\nsize = 64\n')
        files.append(str(f))
    cases = [([files[0], "--held-out", str(tmp_path / "missing.toml")], "no such mission file"),
             ([files[0], f"a={files[1]}", "--held-out", files[1]], "two sites share a name"),
             ([files[0], "--held-out", f"a={files[1]}"], "is also a training site"),
             ([files[0], "--held-out", files[1], "--rounds", "0"], "--rounds must be >= 1"),
             ([files[0], "--held-out", files[1], "--init", str(tmp_path / "none.safetensors")], "no such predictor file"),
             ([files[0], "--held-out", files[1], "-o", "/proc/pf"], "cannot write to /proc/pf")]
    for args, expect in cases:
        assert expect in _one_line_error(capsys, "federate-predictor", *args), args
    assert not ran


def test_terrain_refuses_a_dem_path_that_would_overwrite_the_map_or_is_not_npy(tmp_path, capsys):
    (tmp_path / "x.npy").write_bytes(b"earlier")
    err = _one_line_error(capsys, "terrain", "mars", tmp_path / "x.npy", "--size", "64", "--dem", tmp_path / "x.npy")
    assert "is the map's own path" in err
    err = _one_line_error(capsys, "terrain", "mars", tmp_path / "y.png", "--size", "64", "--dem", tmp_path / "d.txt")
    assert "give a .npy path" in err
    assert (tmp_path / "x.npy").read_bytes() == b"earlier" and not (tmp_path / "y.png").exists()
    assert main(["terrain", "mars", str(tmp_path / "y.png"), "--size", "64", "--dem", str(tmp_path / "d.npy")]) == 0
    assert np.load(tmp_path / "d.npy").shape == (64, 64) and load_map(tmp_path / "y.png").shape == (64, 64)


def test_a_three_channel_array_of_class_codes_is_refused_not_read_as_black_pixels(tmp_path):
    from fedmap.maps.grid import PALETTE

    codes = np.zeros((64, 64, 3), np.uint8)
    codes[10:20, 10:20] = 1
    np.save(tmp_path / "codes.npy", codes)
    with pytest.raises(FedmapError, match=r"holding only 0..1: class codes, not colours") as e:
        load_map(tmp_path / "codes.npy")
    assert "\n" not in str(e.value)
    classes = np.zeros((64, 64), np.uint8)
    classes[5:9] = 1
    classes[30:] = 2
    rgb = np.round(PALETTE[classes] * 255).astype(np.uint8)  # a real picture of the palette's colours
    np.save(tmp_path / "rgb.npy", rgb)
    np.testing.assert_array_equal(load_map(tmp_path / "rgb.npy").classes, classes)


@pytest.mark.parametrize("key, value", [("federation.beta1", "1.5"), ("federation.eta", "inf"),
                                        ("federation.tau", "0")])
def test_server_optimiser_settings_are_checked_whatever_the_aggregator(key, value, capsys):
    err = _one_line_error(capsys, "run", "--size", "64", "--set", f"{key}={value}")  # fedavg, the default
    assert "[federation]" in err and value in err


def test_a_map_that_is_not_square_is_cut_to_its_centred_square_with_a_warning(tmp_path, capsys):
    from fedmap.maps.sources import TerrainSource, load_truth

    classes = np.zeros((64, 90), np.uint8)
    classes[:, 13] = 1  # the first column of the centred square, and the last one
    classes[:, 76] = 1
    np.save(tmp_path / "wide.npy", classes)
    truth = load_truth(TerrainSource(kind="map", path=str(tmp_path / "wide.npy")))
    np.testing.assert_array_equal(truth.classes, classes[:, 13:77])
    assert truth.meta["squared"].startswith("the map is 64x90 cells; the run uses its centred 64x64 square")
    assert "columns 13..76" in truth.meta["squared"]
    np.save(tmp_path / "square.npy", classes[:, 13:77])
    assert "squared" not in load_truth(TerrainSource(kind="map", path=str(tmp_path / "square.npy"))).meta
    assert "squared" not in load_truth(TerrainSource(kind="map", path=str(tmp_path / "wide.npy"),
                                                     crop=[0, 64, 0, 64])).meta  # asked for: no warning


def test_a_mission_file_given_to_run_says_which_command_runs_it(tmp_path, capsys):
    f = tmp_path / "m.toml"
    f.write_text("[mission]\nsteps = 5\n")
    err = _one_line_error(capsys, "run", f)
    assert "is a mission file" in err and "fedmap mission" in err


def test_the_outputs_line_lists_maps_only_when_they_were_written(tmp_path, capsys):
    tiny = ["mission", "--size", "64", "--steps", "6", "--sync-every", "3", "--rovers", "2", "--no-animation"]
    for strategies, listed in (("none", False), ("raw", True)):
        out = tmp_path / strategies
        assert main([*tiny, "--strategies", strategies, "-o", str(out)]) == 0
        text = capsys.readouterr().out
        line = " ".join(text[text.index("outputs:"):text.index("wall time:")].split())  # however it was wrapped
        assert ("maps/" in line) is listed and (out / "maps").is_dir() is listed, (strategies, line)


def test_a_mistyped_command_is_answered_before_the_library_loads():
    """A typo answered in 4-7 s (every command's imports, torch among them, came first): the
    command names are checked first, so a typo imports no part of the library."""
    import subprocess
    import sys

    code = ("import sys; from fedmap.cli import main; rc = main(['--quiet', 'misison', '-o', 'x']); "
            "print(rc, 'torch' in sys.modules, any(m.startswith('fedmap.mission') for m in sys.modules))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.stdout.split() == ["2", "False", "False"], r.stdout + r.stderr
    assert r.stderr.strip() == "error: No such command 'misison'. Did you mean 'mission'?"


def test_the_command_list_checked_first_is_the_apps():
    import typer

    from fedmap.cli import COMMANDS, build_app

    assert tuple(typer.main.get_command(build_app()).commands) == COMMANDS
