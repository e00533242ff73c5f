"""Progress bars that torchrl's log lines do not break.

torchrl logs INFO lines on stdout (for instance when a replay buffer's storage is
created); printed while a tqdm bar is drawn, they land inside the bar. A bar made by
:func:`progress_bar` routes the ``torchrl`` logger's stream handlers through
``tqdm.write`` while it is open, so those lines appear above the bar.
"""

from __future__ import annotations

import logging
from typing import Any

from tqdm.auto import tqdm

__all__ = ["progress_bar"]


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


def progress_bar(enabled: bool, **kwargs: Any) -> tqdm | None:
    """A tqdm bar (``kwargs`` as tqdm's: ``total``, ``desc``, ...) or ``None`` if not ``enabled``.

    Close it when done (``bar.close()``): that also gives torchrl's logger its handler back.

    Examples:
        >>> bar = progress_bar(True, total=3, desc="work", disable=True)
        >>> bar.update(3)
        >>> bar.close()
        >>> progress_bar(False, total=3) is None
        True
    """
    return _LogSafeBar(**kwargs) if enabled else None
