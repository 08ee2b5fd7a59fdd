"""Messages and progress of the command line, through the standard `logging` module.

    surfsplat demo --out outputs/demo         # progress and info on stderr, results on stdout
    surfsplat -q eval ...                     # --quiet: warnings and errors only
    surfsplat eval ... -v                     # --verbose: debug messages too (before or after the command)

Where output goes:
- stdout carries what a command was asked for: result tables, the paths it wrote, a viewer's address,
  the summary of a training run. It can be piped or redirected without noise.
- stderr carries everything else, through loggers under "surfsplat" (`logging.getLogger(__name__)`):
  what a command is doing (info), what it had to work around (warning), details for debugging
  (debug). `configure` installs the one handler; library code only logs, so an application
  embedding surfsplat keeps its own logging setup (unconfigured, Python shows warnings only).
- One-line input errors keep their fixed form `surfsplat CMD: error: ...` (cli.main prints them).

Progress: `progress(iterable, total=..., desc=...)` is the one helper every loop uses. On a
terminal it is a tqdm bar; when stderr is not a terminal (a log file, CI, a job scheduler) a bar's
carriage-return redraws would fill the log, so it writes one info line instead each time another
`LINE_PERCENT` of the work is done or `LINE_SECONDS` have passed, and one when it ends. Under
torchrun only rank 0 shows progress and info; other ranks log warnings and errors, prefixed with
their rank. --quiet hides bars too.

An application showing its own progress (a web page) wraps the work in
`with listen_progress(callback):`; every `progress` loop inside it then also calls
`callback(desc, done, total)` as it starts, advances and ends, shown on stderr or not, in the
thread (and context) that runs the work only.
"""

from __future__ import annotations

import logging
import os
import sys
import time
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from typing import Any, TypeVar

from tqdm import tqdm

ROOT = "surfsplat"  # every logger of the package lives under this name
LINE_SECONDS = 10.0  # off a terminal: a progress line at least this often...
LINE_PERCENT = 10.0  # ...and each time this share of the total is done,
LINE_MIN_SECONDS = 2.0  # but never sooner than this after the last line (a fast loop gets its final line only)

_progress_logger = logging.getLogger(f"{ROOT}.progress")

T = TypeVar("T")


def rank() -> int:
    """This process's rank under torchrun (0 when not distributed)."""
    try:
        return int(os.environ.get("RANK", "0"))
    except ValueError:
        return 0


class _Handler(logging.Handler):
    """Writes to the current sys.stderr (looked up per message, so redirections made after
    `configure` are honoured) through tqdm.write, which keeps an active bar intact below the line."""

    def emit(self, record: logging.LogRecord) -> None:
        try:
            tqdm.write(self.format(record), file=sys.stderr)
        except Exception:  # logging must never take the program down
            self.handleError(record)


class _Formatter(logging.Formatter):
    """Info as plain text; warnings and errors named as such; --verbose adds time, level and logger."""

    def __init__(self, verbose: bool, rank_prefix: str) -> None:
        super().__init__("%(asctime)s %(levelname)-7s %(name)s: %(message)s", "%H:%M:%S")
        self.verbose = verbose
        self.rank_prefix = rank_prefix

    def format(self, record: logging.LogRecord) -> str:
        if self.verbose:
            text = super().format(record)
        else:
            text = record.getMessage()
            if record.levelno >= logging.WARNING:
                text = f"{record.levelname.lower()}: {text}"
            if record.exc_info:
                text += "\n" + self.formatException(record.exc_info)
        return self.rank_prefix + text


def configure(level: int = logging.INFO) -> None:
    """Send the package's log records at `level` and above to stderr (the command line's setup).
    Calling it again replaces the previous setup. Ranks other than 0 keep warnings and errors only."""
    root = logging.getLogger(ROOT)
    for handler in [h for h in root.handlers if isinstance(h, _Handler)]:
        root.removeHandler(handler)
    r = rank()
    handler = _Handler()
    handler.setFormatter(_Formatter(verbose=level <= logging.DEBUG, rank_prefix=f"rank {r}: " if r != 0 else ""))
    root.addHandler(handler)
    root.setLevel(level if r == 0 else max(level, logging.WARNING))


def configured_level() -> int:
    """The level `configure` set (NOTSET when the package's logging was never configured)."""
    return logging.getLogger(ROOT).level


def add_options(parser: Any, *, subcommand: bool = False) -> None:
    """-q/--quiet and -v/--verbose on `parser`, stored as `args.log_level`. On a sub-command's parser
    the options only override what was given before the command (`surfsplat -q eval ...` and
    `surfsplat eval ... -q` both work)."""
    import argparse

    default = argparse.SUPPRESS if subcommand else logging.INFO
    group = parser.add_argument_group("messages").add_mutually_exclusive_group()
    group.add_argument(
        "-q",
        "--quiet",
        dest="log_level",
        action="store_const",
        const=logging.WARNING,
        default=default,
        help="warnings and errors only (no progress, no info)",
    )
    group.add_argument(
        "-v",
        "--verbose",
        dest="log_level",
        action="store_const",
        const=logging.DEBUG,
        default=default,
        help="debug messages too, with time and source",
    )


# ------------------------------------------------------------------------------------------ progress
def _quiet() -> bool:
    configured = logging.getLogger(ROOT).level
    return configured != logging.NOTSET and configured > logging.INFO


def _on_terminal() -> bool:
    stream = sys.stderr
    try:
        return bool(stream is not None and stream.isatty())
    except (AttributeError, ValueError):  # closed or replaced by an object without isatty
        return False


def _duration(seconds: float) -> str:
    return tqdm.format_interval(seconds)


class LogProgress:
    """A progress counter that logs lines instead of redrawing a bar (tqdm's update/set_postfix/close
    interface, so a loop does not care which one it has)."""

    def __init__(
        self, iterable: Iterable[Any] | None, total: float | None, desc: str, unit: str, initial: int = 0
    ) -> None:
        self.iterable = iterable
        if total is None and iterable is not None:
            try:
                total = len(iterable)  # type: ignore[arg-type]
            except TypeError:
                total = None
        self.total = total
        self.desc = desc
        self.unit = unit
        self.n = self.initial = initial
        self.postfix = ""
        self.started = self.last_time = time.perf_counter()
        self.last_n = initial
        self.closed = False

    def __iter__(self) -> Iterator[Any]:
        if self.iterable is None:
            raise TypeError("progress without an iterable: call update() instead")
        try:
            for item in self.iterable:
                yield item
                self.update(1)
        finally:
            self.close()

    def __enter__(self) -> LogProgress:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __len__(self) -> int:
        return int(self.total or 0)

    def set_postfix(self, ordered_dict: dict[str, Any] | None = None, refresh: bool = True, **values: Any) -> None:
        items = {**(ordered_dict or {}), **values}
        self.postfix = ", ".join(f"{k} {v}" for k, v in items.items())

    def set_description(self, desc: str | None = None, refresh: bool = True) -> None:
        self.desc = desc or ""

    def update(self, n: float = 1) -> None:
        self.n += n
        now = time.perf_counter()
        due = now - self.last_time >= LINE_SECONDS
        if self.total:
            share = (self.n - self.last_n) * 100.0 / self.total
            due = due or (share >= LINE_PERCENT and now - self.last_time >= LINE_MIN_SECONDS)
        if due:
            self._line(now)

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        if self.n != self.last_n or self.n == self.initial:
            self._line(time.perf_counter(), final=True)

    def _text(self, now: float, final: bool) -> str:
        elapsed = now - self.started
        done = self.n - self.initial
        parts = [f"{self.n:g}/{self.total:g} {self.unit}" if self.total else f"{self.n:g} {self.unit}"]
        if self.total:
            parts[0] += f" ({100.0 * self.n / self.total:.0f}%)"
        parts.append(_duration(elapsed))
        if done > 0 and elapsed > 0:
            rate = done / elapsed
            parts.append(f"{rate:.2f} {self.unit}/s" if rate >= 1 else f"{1 / rate:.2f} s/{self.unit}")
            if self.total and not final and self.n < self.total:
                parts.append(f"eta {_duration((self.total - self.n) / rate)}")
        if self.postfix:
            parts.append(self.postfix)
        return f"{self.desc}: " + ", ".join(parts) if self.desc else ", ".join(parts)

    def _line(self, now: float, final: bool = False) -> None:
        _progress_logger.info(self._text(now, final))
        self.last_time, self.last_n = now, self.n


def progress(
    iterable: Iterable[T] | None = None,
    *,
    total: float | None = None,
    desc: str = "",
    unit: str = "it",
    initial: int = 0,
    enabled: bool = True,
    leave: bool = True,
) -> Any:
    """`iterable` with progress (or, without one, a counter to `update()`): a tqdm bar on a terminal,
    periodic log lines elsewhere, nothing when `enabled` is False, under --quiet, or on ranks other
    than 0. The object has tqdm's update / set_postfix / close and is a context manager."""
    if not enabled or rank() != 0 or _quiet():
        bar = tqdm(iterable, total=total, initial=initial, disable=True)
    elif _on_terminal():
        bar = tqdm(
            iterable, total=total, desc=desc or None, unit=unit, initial=initial, dynamic_ncols=True, leave=leave
        )
    else:
        bar = LogProgress(iterable, total, desc, unit, initial)
    listener = _listener.get()
    return bar if listener is None else _Reported(bar, iterable, total, desc, initial, listener)


ProgressListener = Callable[[str, float, float | None], None]  # (desc, done, total or None)
_listener: ContextVar[ProgressListener | None] = ContextVar("surfsplat_progress_listener", default=None)


@contextmanager
def listen_progress(callback: ProgressListener) -> Iterator[None]:
    """Within: every `progress` loop of this thread also reports `callback(desc, done, total)` when it
    starts, after each step and when it ends (disabled bars too: the listener has its own display).
    An exception raised by the callback ends the loop that called it (how an application cancels)."""
    token = _listener.set(callback)
    try:
        yield
    finally:
        _listener.reset(token)


class _Reported:
    """A progress bar that also tells a listener how far it is (same interface as the bar)."""

    def __init__(self, bar: Any, iterable: Iterable[Any] | None, total, desc: str, initial: int, listener) -> None:
        if total is None and iterable is not None:
            try:
                total = len(iterable)  # type: ignore[arg-type]
            except TypeError:
                total = None
        self.bar, self.total, self.desc, self.n, self.listener = bar, total, desc, initial, listener
        self.listener(desc, self.n, total)

    def __iter__(self) -> Iterator[Any]:
        for item in self.bar:
            yield item
            self.n += 1
            self.listener(self.desc, self.n, self.total)

    def update(self, n: float = 1) -> None:
        self.bar.update(n)
        self.n += n
        self.listener(self.desc, self.n, self.total)

    def __len__(self) -> int:
        return len(self.bar)

    def __enter__(self) -> _Reported:
        return self

    def __exit__(self, *exc: object) -> None:
        self.bar.close()

    def __getattr__(self, name: str) -> Any:  # set_postfix, set_description, close: the bar's own
        return getattr(self.bar, name)
