"""Progress bars: torchrl's log lines go above an open bar, and its handler comes back;
without a terminal, a few lines per bar instead of redraws."""

from __future__ import annotations

import io
import logging
import os
import subprocess
import sys
from pathlib import Path

import pytest

from dorp_rl import progress
from dorp_rl.progress import LINE_MILESTONES, draws_bars, progress_bar


class Terminal(io.StringIO):
    """A stream that says it is a terminal (where bars are drawn and redrawn)."""

    def isatty(self) -> bool:
        return True


def test_torchrl_log_lines_go_above_an_open_bar_and_the_handler_comes_back():
    logger = logging.getLogger("torchrl")
    before = list(logger.handlers)
    bar = progress_bar(True, total=4, desc="work", file=Terminal())
    assert isinstance(bar, progress._LogSafeBar)  # a terminal gets a tqdm bar
    during = list(logger.handlers)
    streams = [h for h in before if type(h) is logging.StreamHandler]
    assert streams and not any(h in during for h in streams)  # each replaced while open
    assert len(during) == len(before)
    bar.update(2)
    bar.close()
    assert logger.handlers == before
    bar.close()  # closing twice is harmless
    assert logger.handlers == before


def test_no_bar_when_disabled_leaves_the_logger_alone():
    logger = logging.getLogger("torchrl")
    before = list(logger.handlers)
    assert progress_bar(False, total=4) is None
    assert logger.handlers == before


@pytest.mark.parametrize("terminal", [True, False])
def test_collect_play_data_keeps_torchrl_lines_out_of_its_bar(tmp_path, monkeypatch, terminal):
    from dorp_rl.data import collect_play_data
    from dorp_rl.envs import ObjectRearrangementEnv

    # Bar and torchrl's handler on one stream, as on a console; a collection into a
    # folder makes torchrl log "Initialized LazyMemmapStorage" while the bar is open.
    out = Terminal() if terminal else io.StringIO()
    monkeypatch.setattr(sys, "stderr", out)
    handler = logging.StreamHandler(out)
    handler.setFormatter(logging.Formatter("[torchrl] %(message)s"))
    logger = logging.getLogger("torchrl")
    monkeypatch.setattr(logger, "handlers", [handler])
    level = logger.level
    logger.setLevel(logging.INFO)
    try:
        env = ObjectRearrangementEnv(num_objects=1, batch_size=(4,), seed=0)
        collect_play_data(env, 64, directory=tmp_path / "play", seed=0, progress=True)
    finally:
        logger.setLevel(level)
    lines = out.getvalue().split("\n")
    logged = [line for line in lines if "Initialized LazyMemmapStorage" in line]
    assert len(logged) == 1
    # The line starts on a line of its own: after the bar's last "\r" (a terminal), or
    # at the start of a line (no terminal, where nothing is redrawn).
    assert logged[0].split("\r")[-1].startswith("[torchrl] Initialized")
    assert ("play data:" in logged[0]) is terminal  # the bar was drawn on that line first
    assert ("\r" in out.getvalue()) is terminal
    assert logger.handlers == [handler]


def test_relayed_bars_become_events_and_a_mirror_draws_them(monkeypatch):
    events: list[tuple] = []
    clock = iter(float(t) for t in range(100))
    monkeypatch.setattr(progress.time, "monotonic", lambda: next(clock) * 0.2)
    progress.relay_bars(events.append)
    try:
        bar = progress_bar(True, total=10, desc="codes", initial=2)
        assert isinstance(bar, progress._RelayedBar)  # nothing drawn in this process
        for _ in range(8):
            bar.update(1)
        bar.set_postfix({"loss": "1.5"})
        bar.close()
    finally:
        progress.relay_bars(None)
    assert isinstance(progress_bar(True, total=1, disable=True), progress._LogSafeBar)
    assert events[0][0] == "open" and events[0][2] == {"total": 10, "initial": 2, "desc": "codes"}
    updates = [e for e in events if e[0] == "update"]
    assert 1 < len(updates) < 9  # at most one every 0.5 s (clock steps of 0.2 s), one at close
    assert sum(e[2] for e in updates) == 8 and updates[-1][3] == {"loss": "1.5"}
    assert events[-1] == ("close", events[0][1])

    monkeypatch.undo()
    for out in (Terminal(), io.StringIO()):  # drawn as a bar, and as lines
        mirror = progress.BarMirror(file=out, mininterval=0)
        for event in events:
            mirror.show(event, prefix="[3obj] ")
        assert mirror.finished == {"[3obj] codes": 10}
        assert "[3obj] codes" in out.getvalue() and "loss=1.5" in out.getvalue()
        assert ("\r" in out.getvalue()) is isinstance(out, Terminal)
        mirror.show(("update", "unknown", 1, None))  # a bar never opened here is ignored


def test_only_a_terminal_draws_bars(tmp_path):
    assert draws_bars(Terminal()) and not draws_bars(io.StringIO())
    with open(tmp_path / "log.txt", "w") as log:
        assert not draws_bars(log)
    assert not draws_bars(log)  # isatty() of a closed file raises: no bars
    assert not isinstance(progress_bar(True, total=3, file=io.StringIO()), progress._LogSafeBar)


def test_without_a_terminal_a_bar_is_a_line_per_milestone():
    out = io.StringIO()
    bar = progress_bar(True, total=1000, desc="codes", unit="step", file=out)
    for i in range(1000):
        bar.update(1)
        if i == 500:
            bar.set_postfix({"loss": "0.25"})
    bar.close()
    bar.close()  # once only
    lines = out.getvalue().splitlines()
    assert "\r" not in out.getvalue()
    assert lines[0] == "codes: started, 0/1000 step"
    assert [line.split(" (")[0] for line in lines[1:-1]] == [
        f"codes: {int(m * 1000)}/1000 step" for m in LINE_MILESTONES
    ]
    assert "(25%)" in lines[1] and "so far, about" in lines[1] and "left" in lines[1]
    assert "loss" not in lines[1] and lines[3].endswith(", loss=0.25")  # postfix once set
    assert lines[-1].startswith("codes: done 1000/1000 step in ") and len(lines) == 5

    # A resumed bar starts at its initial count: no lines for milestones already passed.
    out = io.StringIO()
    bar = progress_bar(True, total=100, initial=60, desc="codes", file=out)
    bar.update(30)
    bar.close()
    lines = out.getvalue().splitlines()
    assert [line.split(",")[0].split(" (")[0] for line in lines] == [
        "codes: started",
        "codes: 90/100 it",
        "codes: stopped at 90/100 it in 00:00",
    ]


def test_without_a_terminal_a_bar_without_total_prints_every_interval(monkeypatch):
    now = [0.0]
    monkeypatch.setattr(progress.time, "monotonic", lambda: now[0])
    out = io.StringIO()
    bar = progress_bar(True, desc="frames", unit="frame", file=out)
    for _ in range(100):  # 100 updates over 25 intervals
        now[0] += progress.LINE_INTERVAL / 4
        bar.update(10)
    bar.close()
    lines = out.getvalue().splitlines()
    assert len(lines) == 1 + 25 + 1
    assert lines[1] == "frames: 40 frame, 05:00 so far"
    assert lines[-1] == "frames: done 1000 frame in 2:05:00"


#: 1-object codes of a few steps (as conftest's DorpCommand.CODES) on 2048 play frames
TINY_CODES = (
    "--setting", "1obj",
    "--codes.num-frames", "2048",
    "--codes.num-envs", "16",
    "--codes.encoder.code-sizes", "8",
    "--codes.batch-size", "32",
    "--codes.num-steps", "5",
)  # fmt: skip


def test_a_command_logged_to_a_file_writes_a_few_lines_per_bar(tmp_path):
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    with open(tmp_path / "err.txt", "w") as err, open(tmp_path / "out.txt", "w") as out:
        done = subprocess.run(
            [sys.executable, "-m", "dorp_rl", "build-graph", "--root", str(tmp_path),
             "--name", "run", *TINY_CODES],
            stdout=out, stderr=err, env=env, cwd=Path(__file__).parent, timeout=600,
        )  # fmt: skip
    logged = (tmp_path / "err.txt").read_text()
    assert done.returncode == 0, logged
    printed = (tmp_path / "out.txt").read_text()
    assert "\r" not in logged + printed  # no redraws
    bars = {line.split(":")[0] for line in logged.splitlines() if ": started, " in line}
    assert {"play data", "representation", "encode play data"} <= bars
    for bar in bars:  # a start, at most one line per milestone, an end
        lines = [line for line in logged.splitlines() if line.startswith(f"{bar}: ")]
        assert 2 <= len(lines) <= 2 + len(LINE_MILESTONES), lines
    assert len(logged.splitlines()) <= len(bars) * (2 + len(LINE_MILESTONES)) + 5, logged
    assert "graph: done in" in printed
