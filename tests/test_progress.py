"""Progress bars: torchrl's log lines go above an open bar, and its handler comes back."""

from __future__ import annotations

import io
import logging

from dorp_rl.progress import progress_bar


def test_torchrl_log_lines_go_above_an_open_bar_and_the_handler_comes_back():
    logger = logging.getLogger("torchrl")
    before = list(logger.handlers)
    out = io.StringIO()
    bar = progress_bar(True, total=4, desc="work", file=out)
    assert bar is not None
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


def test_collect_play_data_keeps_torchrl_lines_out_of_its_bar(capsys):
    from dorp_rl.data import collect_play_data
    from dorp_rl.envs import ObjectRearrangementEnv

    logger = logging.getLogger("torchrl")
    before = list(logger.handlers)
    env = ObjectRearrangementEnv(num_objects=1, batch_size=(4,), seed=0)
    collect_play_data(env, 64, seed=0, progress=True)
    captured = capsys.readouterr()
    # torchrl's lines, if any, start on a line of their own instead of after a bar's "\r".
    for line in (captured.out + captured.err).split("\n"):
        if "[torchrl]" in line:
            assert "play data" not in line
    assert logger.handlers == before


def test_relayed_bars_become_events_and_a_mirror_draws_them(monkeypatch):
    from dorp_rl import progress

    events: list[tuple] = []
    clock = iter(float(t) for t in range(100))
    monkeypatch.setattr(progress.time, "monotonic", lambda: next(clock) * 0.2)
    progress.relay_bars(events.append)
    try:
        bar = progress_bar(True, total=10, desc="codes", initial=2)
        assert not isinstance(bar, progress._LogSafeBar)  # nothing drawn in this process
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

    out = io.StringIO()
    mirror = progress.BarMirror(file=out, mininterval=0)
    for event in events:
        mirror.show(event, prefix="[3obj] ")
    assert mirror.finished == {"[3obj] codes": 10}
    assert "[3obj] codes" in out.getvalue() and "loss=1.5" in out.getvalue()
    mirror.show(("update", "unknown", 1, None))  # a bar never opened here is ignored
