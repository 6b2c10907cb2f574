"""Progress bars for long steps (tqdm on stderr), silenced by ``enabled=False``."""

from __future__ import annotations

import sys
from collections.abc import Iterable

from tqdm.auto import tqdm

from ._interrupt import check_interrupt


#: Seconds between a bar's frames where stderr is not a terminal (a log file, a batch job's output).
LOG_INTERVAL_S = 30.0


class _Bar(tqdm):
    """A bar whose every step first acts on an interrupt that was requested (:func:`check_interrupt`).

    Its count is brought up to date after every step, not only when a frame is drawn (tqdm's own
    iteration keeps it aside until then): a frame drawn by ``set_postfix_str`` at the start of a
    step, which names the step, would otherwise show the count of the last frame (``0/5`` on the
    fifth of five in a log file, where frames are half a minute apart)."""

    def __iter__(self):
        if self.disable:
            yield from _checked(self.iterable)
            return
        try:
            for item in self.iterable:
                check_interrupt()
                yield item
                self.update(1)  # draws a frame only when mininterval has passed
        finally:
            self.close()


def _checked(iterable: Iterable):
    for item in iterable:
        check_interrupt()
        yield item


def progress_bar(iterable: Iterable, *, desc: str, enabled: bool = True, total: int | None = None):
    """Wrap ``iterable`` in a progress bar when ``enabled``; either way each step first acts on an
    interrupt that was requested and lost inside JAX (:mod:`quadshank.common._interrupt`)."""
    if not enabled:
        return _checked(iterable)

    # where stderr is a log file (not a terminal, nor a notebook's bar), a frame every half minute, not ten a second
    quiet = not (hasattr(sys.stderr, "isatty") and sys.stderr.isatty()) and "ipykernel" not in sys.modules
    return _Bar(iterable, desc=desc, total=total, file=sys.stderr, leave=False, dynamic_ncols=True,
                mininterval=LOG_INTERVAL_S if quiet else 0.1)


def write_above_bars(text: str, file=None) -> None:
    """Print ``text`` as its own line (to stderr by default) above any progress bar being drawn,
    which is drawn again below it: printed plainly, a warning raised inside a step with a bar
    would share the bar's line, and the bar's next redraw would overwrite it."""
    tqdm.write(text, file=sys.stderr if file is None else file)
