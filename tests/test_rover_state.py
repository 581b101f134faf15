"""Rovers that share a state folder (the docs' ``--state /var/lib/fedmap``) keep their own
files, and a second process of the same rover on it is refused."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from fedmap.errors import FedmapError
from fedmap.flower.mission.task import hold_state, state_file
from fedmap.mission.network.remote import Order


def test_two_rovers_on_one_state_folder_keep_their_own_files(tmp_path):
    order = Order("raw", 0, 1, 5, False, [], "m1")
    files = {state_file(tmp_path, order, k) for k in range(4)}
    assert len(files) == 4 and all(f.parent == tmp_path for f in files)
    assert state_file(tmp_path, order, 2).name == "m1-raw-rover2.pickle"


def test_a_second_process_of_the_same_rover_is_refused_and_the_first_one_exiting_frees_it(tmp_path):
    fd0 = hold_state(tmp_path, 0)
    fd1 = hold_state(tmp_path, 1)  # another rover: its own lock
    code = f"from fedmap.flower.mission.task import hold_state; hold_state({str(tmp_path)!r}, 0)"
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode != 0 and f"another rover 0 process (PID {os.getpid()})" in r.stderr
    with pytest.raises(FedmapError, match="another rover 1 process"):
        hold_state(tmp_path, 1)
    os.close(fd0)
    os.close(fd1)
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
