"""What every command shares: the app, the consoles, one-line errors, and progress that also works off a terminal."""

from __future__ import annotations

import signal
import time
from contextlib import contextmanager
from typing import Callable, Iterator

import typer
from rich.console import Console
from rich.markup import escape

from democheck.errors import DemocheckError

BY_ID = (" Or a hub repository id (ORG/NAME): LeRobot's copy under HF_LEROBOT_HOME, else the hub's cache, downloading "
         "what is missing when online (HF_HUB_OFFLINE=1: the cache alone).")
REVISION_HELP = "With a hub repository id: the branch, tag or commit to read."


def local_dataset(dataset, revision: str | None = None):
    """The folder of a dataset given by path or by hub repository id (``data.hub.resolve``)."""
    from democheck.data.hub import resolve

    return resolve(dataset, revision)

app = typer.Typer(
    name="democheck",
    help="Audit robot demonstration datasets: find the demos a learner cannot tell the task from.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
console = Console()
err_console = Console(stderr=True)
_ctrl_c = {"pressed": False}


def answer_ctrl_c() -> None:
    """From now on Ctrl-C also leaves a mark, so that ``user_errors`` recognises it when a library turns the
    interrupt into an error of its own (ctypes, loading a GL library, reports ``ArgumentError: KeyboardInterrupt``)."""

    def pressed(signum, frame):
        _ctrl_c["pressed"] = True
        raise KeyboardInterrupt

    signal.signal(signal.SIGINT, pressed)


def ctrl_c_pressed() -> bool:
    return _ctrl_c["pressed"]


@contextmanager
def user_errors() -> Iterator[None]:
    """Bad input becomes one line on stderr and exit status 2, never a traceback; Ctrl-C exit status 130."""
    try:
        yield
    except DemocheckError as exc:
        err_console.print(f"[bold red]error:[/] {escape(str(exc))}", highlight=False, soft_wrap=True)
        raise typer.Exit(2) from None
    except KeyboardInterrupt:
        raise typer.Exit(130) from None  # the entry point (democheck.__main__) says so in one line
    except Exception:
        if not ctrl_c_pressed():
            raise
        raise typer.Exit(130) from None


def clock(seconds: float) -> str:
    """A duration as people say it: 45 s, 12 min, 3.5 h."""
    return f"{seconds:.0f} s" if seconds < 90 else f"{seconds / 60:.0f} min" if seconds < 5400 else \
        f"{seconds / 3600:.1f} h"


class Bar:
    """Progress of one command: a rich progress bar on a terminal; elsewhere (a log file, CI) a line on stderr
    at every tenth of a stage and at least every 30 s, so long work is never silent."""

    def __init__(self, label: str, unit: str = "", info: bool = False):
        self.label, self.unit, self.tty = label, unit, err_console.is_terminal
        self.stage, self.last, self.info = label, (0.0, -1), ""
        self.began = (time.monotonic(), 0)  # when the stage began, and how far it was
        self.progress = self.job = None
        if self.tty:
            from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn,
                                       TimeRemainingColumn)

            cols = [TextColumn("[bold]{task.description}[/]"), BarColumn(), MofNCompleteColumn(),
                    TextColumn(unit), *([TextColumn("{task.fields[info]}")] if info else []), TimeElapsedColumn(),
                    TimeRemainingColumn()]
            self.progress = Progress(*cols, console=err_console, transient=True)

    def __enter__(self) -> "Bar":
        if self.progress is not None:
            self.progress.__enter__()
            self.job = self.progress.add_task(self.label, total=None, info="")
        return self

    def __exit__(self, *exc) -> None:
        if self.progress is not None:
            self.progress.__exit__(*exc)

    def update(self, done: int, total: int | None, stage: str | None = None, info: str | None = None) -> None:
        if stage is not None and stage != self.stage:
            self.stage, self.last, self.began = stage, (0.0, -1), (time.monotonic(), done)
        if info is not None:
            self.info = info
        if self.progress is not None:
            self.progress.update(self.job, completed=done, total=total, description=self.stage, info=self.info)
            return
        now, tenth = time.monotonic(), (10 * done // total if total else -1)
        if done == total or tenth > self.last[1] or now - self.last[0] > 30:
            self.last = (now, tenth)
            of = f"/{total}" if total else ""
            err_console.print(f"{self.stage}: {done}{of} {self.unit} {self.info}{self.pace(done, total, now)}".rstrip(),
                              highlight=False)

    def pace(self, done: int, total: int | None, now: float) -> str:
        """How fast the stage goes and, where its total is known, how long it has left: " (12.3/s, 4 min left)"."""
        began, at = self.began
        if now - began < 1 or done <= at:
            return ""
        rate = (done - at) / (now - began)
        left = f", {clock((total - done) / rate)} left" if total and done < total else ""
        return f" ({rate:.3g}/s{left})"

    def callback(self, stage: str | None = None) -> Callable[[int, int], None]:
        """An ``on_progress(done, total)`` for library functions, optionally naming the stage."""
        return lambda done, total: self.update(done, total, stage)

    def say(self, text: str) -> None:
        """A line above the bar (a new stage of a long command)."""
        self.stage, self.last, self.began = text, (time.monotonic(), 0), (time.monotonic(), 0)
        if self.progress is not None:
            self.progress.update(self.job, completed=0, total=None, description=text)
        err_console.print(text, highlight=False)


def parse_counts(text: str, option: str) -> dict[str, int]:
    """``kind=count`` pairs separated by commas."""
    out = {}
    for part in text.split(","):
        key, _, value = part.partition("=")
        if not key.strip() or not value.strip().isdigit():
            raise DemocheckError(f"{option} takes kind=count pairs separated by commas, e.g. idle=4,random=4; got {text!r}")
        out[key.strip()] = int(value)
    return out


def short(x: float) -> str:
    """A score in about 5 characters: 3 significant digits, 2 decimals when that is shorter, whole numbers from
    100 up."""
    if abs(x) >= 100:
        return f"{x:.0f}"
    text = f"{x:.3g}"
    return text if len(text) <= 5 else f"{x:.2f}"
