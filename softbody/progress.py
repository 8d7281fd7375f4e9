"""Progress of long commands: a bar on a terminal, a plain line at least every ~10 s on a pipe.

One small helper shared by ``softbody run``, ``bench``, ``advise``, the optimisation loops
of :mod:`softbody.control` and the examples, so that no command stays silent while it
compiles or runs::

    from softbody import progress

    progress.say("meshing the cantilever")               # one line, flushed
    with progress.task("compiling the rollout"):          # a line now, "still ..." lines
        traj = rollout(...)                               # every ~10 s, a done line at the end
    with progress.task("cases", total=len(cases)) as t:   # a bar on a terminal,
        for case in cases:                                # a line per case on a pipe
            run(case)
            t.advance(note=f"{case}: {seconds:.1f} s")

Where it goes: ``sys.stdout`` (looked up on every line, so redirections and pytest's
capture see it). When that is a terminal, open tasks show as a rich progress display
(spinner, bar, count, elapsed time) and lines print above it; otherwise (a pipe, a file)
every line is plain text, prefixed by the seconds since the process started and flushed
at once, and while any task is open a background thread prints a ``still ...`` line
whenever nothing was printed for :data:`EVERY` seconds. That thread is what keeps a single
long compiled call (one XLA program: a whole rollout, which cannot report per step without
host callbacks, and those would keep it out of the persistent compilation cache) from
being a silent wait.

Environment:

* ``SOFTBODY_PROGRESS``: ``bar`` or ``plain`` forces a mode; ``auto`` (default) picks the
  bar on a terminal.
* ``SOFTBODY_PROGRESS_EVERY``: seconds of silence before a ``still ...`` line (default 8).

:func:`remember` / :func:`recall` keep how long a named phase took last time (in
``$SOFTBODY_CACHE_DIR/timings.json``), so that a compile can be announced with its likely
duration.
"""

from __future__ import annotations

import contextlib
import json
import os
import sys
import threading
import time

#: Seconds of silence on a pipe before a ``still ...`` line: 8, so that with the thread's
#: half-second polling and a busy machine the gaps stay under 10 s.
EVERY = float(os.environ.get("SOFTBODY_PROGRESS_EVERY", "8"))
#: The least time between two plain lines of the same task's :meth:`Task.advance` calls (s);
#: a faster loop prints fewer lines, never fewer than one per :data:`EVERY` seconds.
MIN_INTERVAL = 1.0


def _process_start() -> float:
    """The process's start on the :func:`time.monotonic` clock (Linux), else now."""
    try:
        with open("/proc/self/stat") as f:
            started = int(f.read().rsplit(")", 1)[1].split()[19]) / os.sysconf("SC_CLK_TCK")
        with open("/proc/uptime") as f:
            uptime = float(f.read().split()[0])
        ago = uptime - started
        return time.monotonic() - ago if 0 <= ago < 3600 else time.monotonic()
    except (OSError, ValueError, IndexError):
        return time.monotonic()


_START = _process_start()


def elapsed() -> float:
    """Seconds since the process started (since this module was imported where that is unknown)."""
    return time.monotonic() - _START


def _stamp(text: str) -> str:
    return f"[{elapsed():6.1f} s] {text}"


def _span(seconds: float) -> str:
    return f"{seconds:.1f} s" if seconds < 60 else f"{int(seconds // 60)} min {seconds % 60:02.0f} s"


class Task:
    """A unit of work in progress, from :func:`task`: a count (when ``total`` is given) and a note."""

    def __init__(self, reporter: _Reporter, label: str, total: int | None, unit: str):
        self.reporter, self.label, self.total, self.unit = reporter, label, total, unit
        self.completed = 0
        self.note = ""
        self.start = time.monotonic()
        self.printed = 0.0  # when this task's last plain line was printed
        self.rich_id = None

    @property
    def seconds(self) -> float:
        return time.monotonic() - self.start

    def count(self) -> str:
        if self.total is None:
            return f"{self.completed} {self.unit}".rstrip() if self.completed else ""
        return f"{self.completed}/{self.total} {self.unit}".rstrip()

    def advance(self, n: int = 1, note: str | None = None) -> None:
        """Count ``n`` more done; ``note`` (e.g. the case just finished and its time) is shown with it."""
        self.update(self.completed + n, note)

    def update(self, completed: int | None = None, note: str | None = None) -> None:
        """Set the count and/or the note; on a pipe prints a line (at most one per
        :data:`MIN_INTERVAL` seconds, always for the last of ``total``)."""
        if completed is not None:
            self.completed = int(completed)
        if note is not None:
            self.note = note
        self.reporter.updated(self)

    def line(self, still: bool = False) -> str:
        parts = [p for p in (self.count(), self.note) if p]
        what = f"{self.label}: " + ("still running, " if still else "")
        return what + ", ".join(parts + [f"{_span(self.seconds)}"])


class _Reporter:
    def __init__(self):
        self.lock = threading.RLock()
        self.tasks: list[Task] = []
        self.last = time.monotonic()
        self.thread = None
        self.live = None  # a rich Progress while tasks are open on a terminal

    # -- where lines go ---------------------------------------------------------------
    @staticmethod
    def terminal() -> bool:
        mode = os.environ.get("SOFTBODY_PROGRESS", "auto").lower()
        if mode in ("bar", "plain"):
            return mode == "bar"
        try:
            return sys.stdout.isatty()
        except (AttributeError, ValueError):
            return False

    def emit(self, text: str) -> None:
        with self.lock:
            if self.live is not None:
                self.live.console.print(text, highlight=False, markup=False, soft_wrap=True)
            else:
                print(_stamp(text), file=sys.stdout, flush=True)
            self.last = time.monotonic()

    # -- tasks ------------------------------------------------------------------------
    def open(self, task: Task, announce: bool, detail: str = "") -> None:
        with self.lock:
            self.tasks.append(task)
            if self.terminal() and self.live is None and len(self.tasks) == 1:
                self.live = self._start_live()
            if self.live is not None:
                task.rich_id = self.live.add_task(task.label, total=task.total, note="")
                if detail:
                    self.emit(f"{task.label} ({detail})")
            elif announce:
                self.emit(f"{task.label} ({detail}) ..." if detail else f"{task.label} ...")
                task.printed = time.monotonic()
            if self.live is None and (self.thread is None or not self.thread.is_alive()):
                self.thread = threading.Thread(target=self._watch, name="softbody-progress", daemon=True)
                self.thread.start()

    def updated(self, task: Task) -> None:
        with self.lock:
            if self.live is not None and task.rich_id is not None:
                self.live.update(task.rich_id, completed=task.completed, note=task.note)
                return
            now = time.monotonic()
            last_one = task.total is not None and task.completed >= task.total
            if now - task.printed >= MIN_INTERVAL or last_one:
                self.emit(task.line())
                task.printed = now

    def close(self, task: Task, summary: str | None) -> None:
        with self.lock:
            if task in self.tasks:
                self.tasks.remove(task)
            if self.live is not None and task.rich_id is not None:
                self.live.remove_task(task.rich_id)
            if summary is not None:
                self.emit(summary)
            if self.live is not None and not self.tasks:
                self.live.stop()
                self.live = None

    def _start_live(self):
        from rich.console import Console
        from rich.errors import LiveError
        from rich.progress import (
            BarColumn,
            MofNCompleteColumn,
            Progress,
            SpinnerColumn,
            TextColumn,
            TimeElapsedColumn,
        )

        live = Progress(SpinnerColumn(), TextColumn("[bold]{task.description}"), BarColumn(),
                        MofNCompleteColumn(), TimeElapsedColumn(), TextColumn("{task.fields[note]}"),
                        console=Console(file=sys.stdout), transient=True)
        try:
            live.start()
        except LiveError:  # another rich live display (e.g. the caller's own) is running
            return None
        return live

    def _watch(self) -> None:
        while True:
            time.sleep(min(0.5, EVERY / 4))
            with self.lock:
                if not self.tasks:
                    self.thread = None
                    return
                if self.live is None and time.monotonic() - self.last >= EVERY:
                    try:
                        self.emit(self.tasks[-1].line(still=True))
                    except (OSError, ValueError):  # stdout closed (a pipe's reader left): stop quietly
                        self.thread = None
                        return


_reporter = _Reporter()


def say(text: str) -> None:
    """Print one progress line now (flushed; above the bar on a terminal)."""
    _reporter.emit(text)


@contextlib.contextmanager
def task(label: str, total: int | None = None, *, unit: str = "", announce: bool = True,
         done: str | None = "done", detail: str = ""):
    """A unit of work that reports while it runs.

    Arguments:
        label: what is being done, e.g. ``"compiling the rollout"`` or ``"bench cases"``.
        total: how many items (steps, cases, iterations) when known: a bar on a terminal.
        unit: the items' name, shown after the count (``"cases"``).
        announce: print ``label ...`` when it starts (on a pipe).
        detail: said once, in parentheses after the label, when it starts.
        done: the word of the line printed when it ends (``"label: done, 3/3, 12.1 s"``);
            ``None`` prints none.

    Yields:
        The :class:`Task`: call ``advance``/``update`` as items finish. Nothing need be
        called for a single opaque step: a ``still ...`` line comes every :data:`EVERY`
        seconds on a pipe (a spinner on a terminal).

    On an exception the end line says ``stopped`` and the exception propagates.
    """
    t = Task(_reporter, label, total, unit)
    _reporter.open(t, announce, detail)
    ok = False
    try:
        yield t
        ok = True
    finally:
        _reporter.close(t, _ending(t, ok, done))


def _ending(t: Task, ok: bool, done: str | None) -> str | None:
    if not ok:
        return f"{t.label}: stopped after {_span(t.seconds)}"
    if done is None:
        return None
    count = f", {t.count()}" if t.count() else ""
    return f"{t.label}: {done}{count} in {_span(t.seconds)}"


class Bar:
    """The part of :class:`rich.progress.Progress` that :func:`softbody.control.optimize.progress_bar`'s
    users call (``add_task``, ``update``), over :func:`task`: a bar on a terminal, lines on a pipe.

    Arguments:
        enabled: ``False`` reports nothing.
    """

    def __init__(self, enabled: bool = True):
        self.enabled = enabled
        self.tasks: list[Task] = []

    def __enter__(self):
        return self

    def __exit__(self, kind, value, traceback):
        for t in reversed(self.tasks):
            _reporter.close(t, _ending(t, kind is None, "done"))
        self.tasks = []
        return False

    def add_task(self, description: str, total=None, completed: int = 0, stats: str = "", **_fields) -> int:
        t = Task(_reporter, description, None if total is None else int(total), "")
        t.completed, t.note = int(completed), stats
        if self.enabled:
            _reporter.open(t, announce=False)
            _reporter.emit(f"{description}: starting" + (f" ({stats})" if stats else ""))
            t.printed = time.monotonic()
            self.tasks.append(t)
        return len(self.tasks) - 1 if self.enabled else -1

    def update(self, task_id: int, completed=None, advance=None, stats: str | None = None, **_fields) -> None:
        if not self.enabled or task_id < 0:
            return
        t = self.tasks[task_id]
        if advance is not None:
            completed = t.completed + advance
        t.update(completed, stats)


def track(items, label: str, *, total: int | None = None, unit: str = "", note=None):
    """Iterate over ``items`` inside a :func:`task`, advancing it after each one.

    Arguments:
        items: an iterable.
        label, unit: as for :func:`task`.
        total: its length (default ``len(items)`` when it has one).
        note: a function of the item just finished giving its note (default ``str``).
    """
    if total is None and hasattr(items, "__len__"):
        total = len(items)
    with task(label, total=total, unit=unit) as t:
        for item in items:
            tick = time.monotonic()
            yield item
            text = str(item) if note is None else note(item)
            t.advance(note=f"{text} ({_span(time.monotonic() - tick)})")


# ------------------------------------------------------------------------------------------
# How long a phase took last time
# ------------------------------------------------------------------------------------------


def _timings_path():
    from softbody.native import cache_dir

    return cache_dir() / "timings.json"


def recall(key: str) -> float | None:
    """Seconds the phase ``key`` took last time in this user's cache, or ``None``."""
    try:
        return float(json.loads(_timings_path().read_text())[key])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def remember(key: str, seconds: float) -> None:
    """Record that phase ``key`` took ``seconds`` (best effort: an unwritable cache is skipped)."""
    try:
        path = _timings_path()
        try:
            data = json.loads(path.read_text())
        except (OSError, ValueError):
            data = {}
        data = data if isinstance(data, dict) else {}
        data[key] = round(float(seconds), 2)
        if len(data) > 200:  # keep the file small: drop the oldest entries
            data = dict(list(data.items())[-200:])
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(f".{os.getpid()}.tmp")
        tmp.write_text(json.dumps(data, indent=0))
        tmp.replace(path)
    except OSError:
        pass


@contextlib.contextmanager
def compiling(what: str, key: str, *, cached: bool | None = None):
    """A :func:`task` around a call that compiles (and runs) one XLA program.

    Its first line gives the likely wait: how long ``key`` took last time (see
    :func:`remember`), and whether the program is kept in the persistent compilation cache
    (``cached``: ``True`` kept after the first run, ``False`` compiled again in every
    process because it holds a host callback, ``None`` unknown). Records the time taken.

    Arguments:
        what: e.g. ``"compiling and running the rollout"``.
        key: names the program for :func:`remember`, e.g. ``"run/cantilever/458/100"``.
        cached: see above.
    """
    hints = []
    last = recall(key)
    hints.append(f"took {_span(last)} last time" if last is not None else "first run of this scene")
    if cached is True:
        hints.append("the compiled program is kept in the cache after the first run")
    elif cached is False:
        hints.append("compiled again in every process: it holds a host callback")
    tick = time.monotonic()
    with task(what, done=None, detail="; ".join(hints)) as t:
        yield t
    seconds = time.monotonic() - tick
    remember(key, seconds)
    say(f"{what}: done in {_span(seconds)}")
