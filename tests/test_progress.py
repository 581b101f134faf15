"""Progress without a terminal: plain lines at stage boundaries and every 10 s, --log-json, --quiet."""

import io
import json
import re
import subprocess
import sys

from fedmap.cli import main
from fedmap.cli.ui import LogProgress, stage_callbacks

TINY = ["demo", "--method", "paper", "--size", "64", "--local-epochs", "2", "--pairs", "5", "--no-central"]
LINE = re.compile(r"^\[\d\d:\d\d:\d\d\] stage '")


class FakeClock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def _reporter(**kw):
    clock, stream = FakeClock(), io.StringIO()
    return LogProgress(clock=clock, stream=stream, heartbeat=False, **kw), clock, stream


def test_lines_at_stage_boundaries_and_every_interval():
    progress, clock, stream = _reporter()
    with progress:
        on_stage, on_step = stage_callbacks(progress)
        on_stage("federated training", 320)
        for step in range(1, 321):
            clock.t += 0.125  # 40 s in all: lines at 10, 20, 30 s, none in between
            on_step(step, 0.5)
        on_stage("render", 0)
        clock.t += 3
    lines = stream.getvalue().splitlines()
    assert all(LINE.match(x) for x in lines), lines
    assert lines[0].endswith("stage 'federated training' started 0/320 (0%)")
    steps = [x for x in lines if "elapsed" in x]
    assert len(steps) == 3
    assert "stage 'federated training' 80/320 (25%) elapsed 10.0 s eta 30.0 s, loss 0.5000" in steps[0]
    assert "done 320/320 (100%) in 40.0 s" in lines[4]
    assert lines[5].endswith("stage 'render' started") and lines[6].endswith("stage 'render' done in 3.0 s")
    assert len(lines) == 7


def test_a_long_step_still_logs_every_interval():
    progress, clock, stream = _reporter()
    with progress:
        task = progress.add_task("waiting for rovers", total=3, loss="")
        for _ in range(6):
            clock.t += 4
            progress.tick()  # what the heartbeat thread calls every second
        progress.update(task, completed=1, description="round 1/3")
    lines = stream.getvalue().splitlines()
    assert sum("elapsed" in x for x in lines) == 2  # at 12 s and 24 s (4 s steps, 10 s interval)
    assert "stage 'waiting for rovers' done" in lines[3] and "stage 'round 1/3' started" in lines[4]


def test_json_lines_and_quiet():
    progress, clock, stream = _reporter(json_lines=True)
    with progress:
        on_stage, on_step = stage_callbacks(progress)
        on_stage("training", 10)
        clock.t += 11
        on_step(1, 0.25)
    events = [json.loads(x) for x in stream.getvalue().splitlines()]
    assert [e["phase"] for e in events] == ["start", "step", "end"]
    assert all(e["event"] == "progress" and e["stage"] == "training" for e in events)
    assert events[1]["done"] == 1 and events[1]["total"] == 10 and events[1]["eta_s"] == 99.0
    assert events[1]["elapsed_s"] == 11.0
    quiet, clock, stream = _reporter(quiet=True)
    with quiet:
        on_stage, on_step = stage_callbacks(quiet)
        on_stage("training", 10)
        clock.t += 20
        on_step(1, 0.25)
    assert stream.getvalue() == ""


def test_piped_demo_prints_progress_lines(tmp_path):
    r = subprocess.run([sys.executable, "-m", "fedmap", *TINY, "-o", str(tmp_path / "a")], capture_output=True,
                       text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    lines = [x for x in r.stdout.splitlines() if LINE.match(x)]
    for stage in ("load terrain", "federated training", "render, refine, evaluate", "write outputs"):
        assert any(f"stage '{stage}' started" in x for x in lines), (stage, r.stdout)
        assert any(f"stage '{stage}' done" in x for x in lines), (stage, r.stdout)
    assert "wall time" in r.stdout


def test_log_json_and_quiet_in_process(tmp_path, capsys):
    assert main([*TINY, "--log-json", "-o", str(tmp_path / "a")]) == 0
    out = capsys.readouterr().out
    events = [json.loads(x) for x in out.splitlines() if x.startswith("{")]
    assert {"load terrain", "federated training", "write outputs"} <= {e["stage"] for e in events}
    assert all(set(e) >= {"event", "stage", "done", "total", "elapsed_s", "eta_s"} for e in events)
    assert not any(LINE.match(x) for x in out.splitlines())
    assert main(["--quiet", *TINY, "-o", str(tmp_path / "b")]) == 0
    out = capsys.readouterr().out
    assert "wall time" in out
    assert not any(LINE.match(x) or x.startswith("{") for x in out.splitlines())


def test_renamed_task_is_a_new_stage():
    """``base-station`` and ``ablate-init`` move one task through stages by renaming it."""
    progress, clock, stream = _reporter()
    with progress:
        task = progress.add_task("waiting for rovers", total=3, loss="")
        clock.t += 5
        progress.update(task, completed=0, description="round 1/3", loss="4 rovers")
        clock.t += 5
        progress.update(task, completed=1, description="round 2/3")
        progress.update(task, completed=3, description="finished")
    lines = [x.split("] ", 1)[1] for x in stream.getvalue().splitlines()]
    assert lines == [
        "stage 'waiting for rovers' started 0/3 (0%)",
        "stage 'waiting for rovers' done 0/3 (0%) in 5.0 s",
        "stage 'round 1/3' started 0/3 (0%)",
        "stage 'round 1/3' done 0/3 (0%) in 5.0 s, 4 rovers",
        "stage 'round 2/3' started 1/3 (33%)",
        "stage 'round 2/3' done 1/3 (33%) in 0.0 s, 4 rovers",
        "stage 'finished' started 3/3 (100%)",
        "stage 'finished' done 3/3 (100%) in 0.0 s, 4 rovers",
    ]


def test_log_json_keeps_stdout_pure_json_lines(tmp_path):
    """With --log-json every stdout line parses as JSON; the human summary goes to stderr."""
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-m", "fedmap", "terrain", "moon", str(tmp_path / "m.png"), "--size", "64",
                        "--log-json"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert all(__import__("json").loads(line) for line in r.stdout.splitlines() if line.strip())
    assert "64x64 moon" in r.stderr


def test_stages_side_by_side_each_end_with_their_own_count():
    """A mission's strategies run side by side: a new one must not end the others (it printed
    "mission: raw done 89/300 (30%)" and "none done 0/300 (0%) in 0.0 s" for strategies that
    ran every step); each ends when its own count is done, and the stage before them ends first."""
    progress, clock, stream = _reporter()
    with progress:
        terrain = progress.add_task("load terrain", total=None, loss="")
        clock.t += 1
        a = progress.add_task("mission: none", total=300, loss="", alongside=True)
        b = progress.add_task("mission: raw", total=300, loss="", alongside=True)
        for step in range(1, 301):
            clock.t += 0.01
            progress.update(a, completed=step)
            if step <= 150:
                progress.update(b, completed=step)
        c = progress.add_task("mission: central", total=300, loss="", alongside=True)
        for step in range(151, 301):
            progress.update(b, completed=step)
            progress.update(c, completed=step)
        progress.update(c, completed=300)
        progress.add_task("write outputs", total=None, loss="")
    lines = stream.getvalue().splitlines()
    done = [x for x in lines if " done" in x]
    assert "stage 'load terrain' done in 1.0 s" in done[0] and terrain == 0
    for name in ("none", "raw", "central"):
        assert any(f"stage 'mission: {name}' done 300/300 (100%)" in x for x in done), lines
    assert not any(re.search(r"mission: \w+' done (?!300/300)", x) for x in lines), lines
