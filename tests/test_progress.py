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
