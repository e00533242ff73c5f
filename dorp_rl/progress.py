"""Progress bars that torchrl's log lines do not break.

torchrl logs INFO lines on stdout (for instance when a replay buffer's storage is
created); printed while a tqdm bar is drawn, they land inside the bar. A bar made by
:func:`progress_bar` routes the ``torchrl`` logger's stream handlers through
``tqdm.write`` while it is open, so those lines appear above the bar.

Bars of worker processes cannot draw on the parent's terminal without garbling it. In a
worker, :func:`relay_bars` turns every bar of :func:`progress_bar` into events sent to
the parent (a few per second at most), where a :class:`BarMirror` draws them as bars of
its own.

Bars are drawn only on a terminal. When the stream they would go to is not one (a log
file, a batch job, CI), :func:`progress_bar` and :class:`BarMirror` print instead a line
when a bar opens, one at each of :data:`LINE_MILESTONES` of its total (every
:data:`LINE_INTERVAL` seconds when the total is unknown) and one when it closes: a
handful of lines per stage instead of a redraw per update (:func:`draws_bars` decides,
for every bar of the library).
"""

from __future__ import annotations

import itertools
import logging
import os
import sys
import time
from collections.abc import Callable
from typing import Any

from tqdm.auto import tqdm

__all__ = [
    "LINE_INTERVAL",
    "LINE_MILESTONES",
    "BarMirror",
    "draws_bars",
    "progress_bar",
    "relay_bars",
]

#: fractions of a bar's total at which a progress line is printed without a terminal
LINE_MILESTONES = (0.25, 0.5, 0.75)
#: seconds between progress lines without a terminal when a bar's total is unknown
LINE_INTERVAL = 300.0

#: where the bars of this process go as events (see :func:`relay_bars`); None: drawn here
_relay: Callable[[tuple[Any, ...]], None] | None = None
_bar_ids = itertools.count()


class _AboveBarHandler(logging.StreamHandler):
    """Writes records with ``tqdm.write`` (above any open bar), on the stream it replaces."""

    def emit(self, record: logging.LogRecord) -> None:
        try:
            tqdm.write(self.format(record), file=self.stream)
        except Exception:
            self.handleError(record)


class _LogSafeBar(tqdm):
    """A tqdm bar that routes torchrl's console log lines above itself until closed."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        logger = logging.getLogger("torchrl")
        self._logger, self._handlers = logger, list(logger.handlers)
        logger.handlers = [self._above_bar(h) for h in self._handlers]
        super().__init__(*args, **kwargs)

    @staticmethod
    def _above_bar(handler: logging.Handler) -> logging.Handler:
        if type(handler) is not logging.StreamHandler:  # files and others stay as they are
            return handler
        above = _AboveBarHandler(handler.stream)
        above.setLevel(handler.level)
        above.setFormatter(handler.formatter)
        for log_filter in handler.filters:
            above.addFilter(log_filter)
        return above

    def close(self) -> None:
        try:
            super().close()
        finally:
            handlers, self._handlers = getattr(self, "_handlers", None), None
            if handlers is not None:
                self._logger.handlers = handlers


class _RelayedBar:
    """A bar of a worker process: its state goes to the parent as events (see
    :func:`relay_bars`), at most one update every ``interval`` seconds, and at close."""

    interval = 0.5

    def __init__(self, send: Callable[[tuple[Any, ...]], None], **kwargs: Any) -> None:
        self._send = send
        self._key = f"{os.getpid()}:{next(_bar_ids)}"
        self.n = int(kwargs.get("initial", 0))
        self.total = kwargs.get("total")
        self._pending, self._postfix, self._last = 0, None, 0.0
        shown = {k: kwargs[k] for k in ("total", "initial", "desc", "unit") if k in kwargs}
        send(("open", self._key, shown))

    def update(self, n: int = 1) -> None:
        self.n += n
        self._pending += n
        self._flush(force=False)

    def set_postfix(self, ordered_dict: Any = None, refresh: bool = True, **kwargs: Any) -> None:
        self._postfix = {**dict(ordered_dict or {}), **kwargs}
        self._flush(force=False)

    def _flush(self, force: bool) -> None:
        now = time.monotonic()
        if force or now - self._last >= self.interval:
            self._send(("update", self._key, self._pending, self._postfix))
            self._pending, self._last = 0, now

    def close(self) -> None:
        self._flush(force=True)
        self._send(("close", self._key))


def draws_bars(stream: Any = None) -> bool:
    """Whether bars are drawn (redrawn in place) on ``stream`` (default: ``sys.stderr``,
    where tqdm draws): on a terminal or in a notebook, not in a file or a pipe."""
    if any(cls.__module__.startswith("tqdm.notebook") for cls in tqdm.__mro__):
        return True  # a notebook's widget bars (their stderr is no terminal)
    stream = sys.stderr if stream is None else stream
    isatty = getattr(stream, "isatty", None)
    try:
        return bool(isatty and isatty())
    except (ValueError, OSError):  # a closed stream
        return False


class _LineBar:
    """A bar for a stream that is not a terminal: a line when opened, at each of
    :data:`LINE_MILESTONES` of the total (every :data:`LINE_INTERVAL` seconds without a
    total), and when closed; never a carriage return. Has what the library uses of a
    tqdm bar (``update``, ``set_postfix``, ``n``, ``total``, ``close``); other tqdm
    arguments (``leave``, ``mininterval``, ...) are accepted and ignored."""

    def __init__(
        self,
        total: float | None = None,
        initial: float = 0,
        desc: str | None = None,
        unit: str = "it",
        file: Any = None,
        **_tqdm_only: Any,
    ) -> None:
        self.total, self.n = total, initial
        self.desc, self.unit = desc or "progress", unit
        self._file = file
        self._postfix: dict[str, Any] = {}
        self._start = self._last = time.monotonic()
        self._start_n = initial
        self._passed = sum(1 for m in LINE_MILESTONES if self._fraction() >= m)
        self._closed = False
        self._print(f"started, {self._count()}")

    def _fraction(self) -> float:
        return self.n / self.total if self.total else 0.0

    def _count(self) -> str:
        total = "" if self.total is None else f"/{self.total:g}"
        return f"{self.n:g}{total} {self.unit}"

    def _print(self, what: str) -> None:
        postfix = "".join(f", {k}={v}" for k, v in self._postfix.items())
        print(f"{self.desc}: {what}{postfix}", file=self._file or sys.stderr, flush=True)

    def update(self, n: float = 1) -> None:
        self.n += n
        now = time.monotonic()
        spent = now - self._start
        if self.total:
            passed = sum(1 for m in LINE_MILESTONES if self._fraction() >= m)
            if passed > self._passed and self.n < self.total:
                self._passed = passed
                done = (self.n - self._start_n) / (self.total - self._start_n)
                left = tqdm.format_interval(spent * (1 - done) / done)
                self._print(
                    f"{self._count()} ({100 * self._fraction():.0f}%), "
                    f"{tqdm.format_interval(spent)} so far, about {left} left"
                )
        elif now - self._last >= LINE_INTERVAL:
            self._print(f"{self._count()}, {tqdm.format_interval(spent)} so far")
            self._last = now

    def set_postfix(self, ordered_dict: Any = None, refresh: bool = True, **kwargs: Any) -> None:
        self._postfix = {**dict(ordered_dict or {}), **kwargs}

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        spent = tqdm.format_interval(time.monotonic() - self._start)
        ended = "done" if self.total is None or self.n >= self.total else "stopped at"
        self._print(f"{ended} {self._count()} in {spent}")


def _make_bar(**kwargs: Any) -> Any:
    """A bar drawn here: a tqdm bar on a terminal (or when disabled), else a line bar."""
    if kwargs.get("disable") or draws_bars(kwargs.get("file")):
        return _LogSafeBar(**kwargs)
    return _LineBar(**kwargs)


def relay_bars(send: Callable[[tuple[Any, ...]], None] | None) -> None:
    """From now on, bars of :func:`progress_bar` in this process are events given to
    ``send`` (e.g. a multiprocessing queue's ``put``) instead of being drawn; a
    :class:`BarMirror` in the parent draws them. ``None`` draws bars here again."""
    global _relay
    _relay = send


class BarMirror:
    """Draws, in this process, the bars that worker processes relay (:func:`relay_bars`).

    Examples:
        >>> events = []
        >>> relay_bars(events.append)
        >>> bar = progress_bar(True, total=4, desc="codes")
        >>> bar.update(4)
        >>> bar.close()
        >>> relay_bars(None)
        >>> mirror = BarMirror(disable=True)
        >>> for event in events:
        ...     mirror.show(event, prefix="[2obj] ")
        >>> mirror.finished
        {'[2obj] codes': 4}
    """

    def __init__(self, **tqdm_kwargs: Any) -> None:
        self._kwargs = tqdm_kwargs
        self._bars: dict[str, tuple[Any, str]] = {}
        self._counts: dict[str, int] = {}
        #: description -> count of every bar closed so far
        self.finished: dict[str, int] = {}

    def show(self, event: tuple[Any, ...], prefix: str = "") -> None:
        """Applies one event of a relayed bar; ``prefix`` goes before its description."""
        kind, key = event[0], event[1]
        if kind == "open":
            shown = dict(event[2])
            shown["desc"] = prefix + str(shown.get("desc", ""))
            self._bars[key] = (_make_bar(leave=False, **shown, **self._kwargs), shown["desc"])
            self._counts[key] = int(shown.get("initial", 0))
        elif key in self._bars:
            bar, desc = self._bars[key]
            if kind == "update":
                if event[3]:
                    bar.set_postfix(event[3], refresh=False)
                bar.update(event[2])
                self._counts[key] += event[2]
            elif kind == "close":
                self.finished[desc] = self._counts.pop(key)
                self._bars.pop(key)[0].close()

    def close(self) -> None:
        """Closes every bar still open (e.g. of a worker that died)."""
        for key in list(self._bars):
            self._bars.pop(key)[0].close()


def progress_bar(enabled: bool, **kwargs: Any) -> Any:
    """A tqdm bar (``kwargs`` as tqdm's: ``total``, ``desc``, ...) or ``None`` if not ``enabled``.

    Without a terminal (:func:`draws_bars` of ``kwargs["file"]``, default stderr) it is a
    bar of a few lines instead (see the module docstring). Close it when done
    (``bar.close()``): that also gives torchrl's logger its handler back. In a worker
    process after :func:`relay_bars`, the bar is relayed to the parent. Every kind has
    ``update``, ``set_postfix``, ``n``, ``total`` and ``close``.

    Examples:
        >>> bar = progress_bar(True, total=3, desc="work", disable=True)
        >>> bar.update(3)
        >>> bar.close()
        >>> progress_bar(False, total=3) is None
        True
    """
    if not enabled:
        return None
    if _relay is not None:
        return _RelayedBar(_relay, **kwargs)  # type: ignore[return-value]
    return _make_bar(**kwargs)
