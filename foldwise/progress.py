"""Progress of long commands: a rich bar with an ETA on a terminal, plain lines anywhere else.

Rich draws its bars with cursor movements and, when the output is not a terminal, prints
nothing until the bar closes; its tables wrap at 80 columns. A pipe or a log file (``make run |
tee log``) instead gets one plain line per step (or per ``interval_s``), no control codes and
no wrapping: :func:`command_console` and :class:`CommandProgress`.
"""

from __future__ import annotations

import sys
import time
from typing import IO

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)

# Wide enough for every table foldwise prints; a log has no screen edge to wrap at.
PIPE_WIDTH = 500


def command_console(file: IO[str] | None = None, stderr: bool = False) -> Console:
    """A console that is rich on a terminal and plain (no codes, no wrapping) otherwise."""
    stream = file or (sys.stderr if stderr else sys.stdout)
    isatty = getattr(stream, "isatty", None)
    try:
        terminal = bool(isatty and isatty())
    except ValueError:  # a closed stream
        terminal = False
    if terminal:
        return Console(file=file, stderr=stderr)
    return Console(
        file=file, stderr=stderr, width=PIPE_WIDTH, soft_wrap=True, color_system=None, force_terminal=False,
        highlight=False, emoji=False,
    )  # fmt: skip


def format_seconds(seconds: float | None) -> str:
    """``h:mm:ss`` (``-:--:--`` when unknown), the form rich's time columns use."""
    if seconds is None or seconds != seconds or seconds == float("inf"):
        return "-:--:--"
    seconds = max(0, int(round(seconds)))
    return f"{seconds // 3600}:{seconds // 60 % 60:02d}:{seconds % 60:02d}"


def remaining_seconds(elapsed_s: float, done: float, total: float) -> float | None:
    """Time left at the pace so far (None before the first step is done, 0 once finished)."""
    if total <= 0 or done >= total:
        return 0.0
    if done <= 0:
        return None
    return elapsed_s / done * (total - done)


class CommandProgress:
    """``with CommandProgress(console, "training", total=200, unit="iterations") as bar: bar.update(advance=1)``.

    On a terminal: a rich bar (description, bar, done/total, elapsed, ETA). Otherwise a line
    ``description: done/total unit (pct%), elapsed h:mm:ss, ETA h:mm:ss`` whenever at least
    ``interval_s`` passed since the last line (0: a line per update), and always at the end.
    """

    def __init__(
        self,
        console: Console,
        description: str,
        total: float,
        unit: str,
        interval_s: float = 0.0,
        clock=time.monotonic,
    ) -> None:
        self.console = console
        self.description = description
        self.total = total
        self.unit = unit
        self.interval_s = interval_s
        self.completed = 0.0
        self._clock = clock
        self._started = clock()
        self._last_line: float | None = None
        self._last_printed: tuple[float, str] | None = None
        self._bar: Progress | None = None
        self._task = None

    def __enter__(self) -> CommandProgress:
        self._started = self._clock()
        if self.console.is_terminal:
            self._bar = Progress(
                TextColumn("[progress.description]{task.description}"),
                BarColumn(),
                MofNCompleteColumn(),
                TextColumn(self.unit),
                TimeElapsedColumn(),
                TextColumn("ETA"),
                TimeRemainingColumn(),
                console=self.console,
            )
            self._bar.__enter__()
            self._task = self._bar.add_task(self.description, total=self.total)
        return self

    def update(self, completed: float | None = None, *, advance: float = 0, description: str | None = None) -> None:
        if completed is not None:
            self.completed = completed
        self.completed += advance
        if description is not None:
            self.description = description
        if self._bar is not None:
            self._bar.update(self._task, completed=self.completed, description=self.description)
            return
        now = self._clock()
        due = self._last_line is None or now - self._last_line >= self.interval_s
        if due or self.completed >= self.total:
            self._print_line(now)

    def line(self, now: float | None = None) -> str:
        elapsed = (self._clock() if now is None else now) - self._started
        done = int(self.completed) if float(self.completed).is_integer() else round(self.completed, 2)
        total = int(self.total) if float(self.total).is_integer() else self.total
        percent = 100.0 * self.completed / self.total if self.total else 100.0
        eta = remaining_seconds(elapsed, self.completed, self.total)
        return (
            f"{self.description}: {done}/{total} {self.unit} ({percent:.0f}%), "
            f"elapsed {format_seconds(elapsed)}, ETA {format_seconds(eta)}"
        )

    def _print_line(self, now: float) -> None:
        state = (self.completed, self.description)
        if state == self._last_printed:
            return
        self._last_line = now
        self._last_printed = state
        self.console.print(self.line(now), markup=False, highlight=False)

    def __exit__(self, *exc_info) -> None:
        if self._bar is not None:
            self._bar.__exit__(*exc_info)
        elif exc_info[0] is None:
            self._print_line(self._clock())
