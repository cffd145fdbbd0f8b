"""Where the time of a command went: named wall-clock sections, off unless a profile is running.

Code marks a step with ``with section("scene build"): ...``. Outside ``profile()`` a section costs one
global test and a ``nullcontext`` (well under a microsecond), so call sites stay in hot loops. Inside,
each section adds its ``time.perf_counter`` span to an accumulator (total seconds and number of entries).
Nested sections are timed on their own and also inside their parent; the table indents them, so a
parent's row includes its children's time. Sections opened on other threads are counted at top level.
The table's last two columns say when a section was first entered and last left (seconds from the
profile's start): where sections overlap (a thread beside the main one, a wait for worker processes),
the sum of the rows is more than the wall time, and these columns show what ran beside what. Below the
table, each section entered at least ``REPEATED`` times gets a line on its calls: the median, the slowest
and when it began, and how many took over ``SLOW`` times the median. Work beside a loop that holds some of
its iterations shows there (a search's generations held 20-120 ms each by grids made beside it on the
GPU's one queue: bench/results/ab-2026-12-01-s42/README.md), where the sums hide it.

    place3d --profile optimize --max-evals 300     # prints the table on stderr when the command ends
"""

from __future__ import annotations

import contextlib
import sys
import threading
import time

__all__ = ["section", "record", "profile", "enabled", "report", "Profile", "count_start_up_of", "Traced", "traced",
           "task", "untraced"]

#: sections entered at least this often get a line on their calls below the table
REPEATED = 20
#: a call counts as slow over this many times its section's median
SLOW = 3.0
#: calls kept per section for that line (a section in a hot loop keeps its first ones)
KEPT_CALLS = 100_000

_ACTIVE: "Profile | None" = None
_START_PID: "int | None" = None     # whose start the table's start-up line counts from (None: this process)
_NULL = contextlib.nullcontext()


class Profile:
    """Accumulated sections: ``totals[path] = [seconds, calls]``, ``path`` a tuple of nested names,
    ``spans[path] = [first entered, last left]`` in seconds from the profile's start, and ``calls[path]``
    each call's (start, seconds)."""

    def __init__(self):
        self.totals: dict[tuple[str, ...], list] = {}
        self.spans: dict[tuple[str, ...], list] = {}
        self.calls: dict[tuple[str, ...], list] = {}
        self.start = time.perf_counter()
        self.wall = 0.0
        self._local = threading.local()

    def _stack(self) -> list[str]:
        s = getattr(self._local, "stack", None)
        if s is None:
            s = self._local.stack = []
        return s

    @contextlib.contextmanager
    def section(self, name: str):
        stack = self._stack()
        stack.append(name)
        path = tuple(stack)
        t = time.perf_counter()
        try:
            yield
        finally:
            end = time.perf_counter()
            stack.pop()
            self._add(path, end - t, end)

    def _add(self, path: tuple, seconds: float, end: float) -> None:
        acc = self.totals.setdefault(path, [0.0, 0])
        acc[0] += seconds
        acc[1] += 1
        span = self.spans.setdefault(path, [end - seconds - self.start, 0.0])
        span[0] = min(span[0], end - seconds - self.start)
        span[1] = max(span[1], end - self.start)
        kept = self.calls.setdefault(path, [])
        if len(kept) < KEPT_CALLS:
            kept.append((end - seconds - self.start, seconds))

    def table(self) -> str:
        """The sections as an indented text table in first-seen order, with the whole span last."""
        wall = self.wall or (time.perf_counter() - self.start)
        rows = [f"{'section':44s} {'seconds':>9s} {'calls':>7s} {'share':>6s} {'from':>7s} {'to':>7s}"]
        for path, (sec, calls) in _tree_order(self.totals):
            name = "  " * (len(path) - 1) + path[-1]
            first, last = self.spans.get(path, (float("nan"), float("nan")))
            rows.append(f"{name[:44]:44s} {sec:9.3f} {calls:7d} {100 * sec / wall if wall else 0:5.1f}% "
                        f"{first:7.2f} {last:7.2f}")
        top = sum(v[0] for p, v in self.totals.items() if len(p) == 1)
        rows.append(f"{'(not in a section)':44s} {max(wall - top, 0.0):9.3f}")
        rows.append(f"{'total (profile span)':44s} {wall:9.3f}")
        return "\n".join(rows + self.repeated())

    def repeated(self) -> list[str]:
        """A line for each section entered at least ``REPEATED`` times: its calls' median, its slowest call and
        when that began, and how many calls took over ``SLOW`` times the median (of its first ``KEPT_CALLS``)."""
        import statistics

        out = []
        for path, calls in self.calls.items():
            if len(calls) < REPEATED:
                continue
            med = statistics.median(c[1] for c in calls)
            at, worst = max(calls, key=lambda c: c[1])
            slow = sum(1 for c in calls if c[1] > SLOW * med)
            if not out:
                out.append(f"calls of sections entered {REPEATED} times or more (ms; slow: over {SLOW:g}x the median):")
            # the whole path: a step's name may recur under several parents (the table indents them instead)
            name = " / ".join(path)[-42:]
            out.append(f"  {name:42s} median {1e3 * med:8.2f}  slowest {1e3 * worst:8.1f} at {at:6.2f} s  slow {slow}")
        return out


def _tree_order(totals):
    # parents before their children, siblings in first-seen order (dicts keep insertion order; a child
    # can finish before its parent is recorded, so order by each path prefix's first appearance)
    first = {}
    for i, p in enumerate(totals):
        for k in range(1, len(p) + 1):
            first.setdefault(p[:k], i)
    return sorted(totals.items(), key=lambda kv: [first[kv[0][:k]] for k in range(1, len(kv[0]) + 1)])


def enabled() -> bool:
    """Whether a profile is being recorded."""
    return _ACTIVE is not None


def section(name: str):
    """Context manager timing one step under ``name`` while a profile runs; a no-op otherwise."""
    p = _ACTIVE
    return _NULL if p is None else p.section(name)


def record(name: str, seconds: float) -> None:
    """Add a span measured elsewhere (another process's step) as one call of ``name``, nested in the
    section open on this thread, taken to have ended now; a no-op outside a profile."""
    p = _ACTIVE
    if p is not None:
        p._add(tuple(p._stack()) + (name,), float(seconds), time.perf_counter())


@contextlib.contextmanager
def profile(out=None, print_table: bool = True):
    """Record sections for the duration of the block; print the table to ``out`` (stderr) at its end.

    Yields the ``Profile``; the table is printed even if the block raises.
    """
    global _ACTIVE
    prev, p = _ACTIVE, Profile()
    _ACTIVE = p
    try:
        yield p
    finally:
        p.wall = time.perf_counter() - p.start
        _ACTIVE = prev
        if print_table:
            print(report(p, _since_start(p)), file=out or sys.stderr)


def count_start_up_of(pid: int | None) -> None:
    """Count the table's "process start-up" line from the start of process ``pid`` (None: this process).

    ``place3d serve`` names the client for the span of its command: the start-up a user waits for is the
    client's, not the server's age.
    """
    global _START_PID
    _START_PID = pid


class Traced:
    """A task's result with the sections its process recorded while it ran (``traced``): ``calls`` holds
    (path, start, seconds) per call, ``start`` on ``time.perf_counter``'s clock, which is the system's monotonic
    clock (one for every process on Linux, macOS and Windows), so another process's profile can place them."""

    def __init__(self, value, calls: list, label: str | None = None):
        self.value, self.calls, self.label = value, calls, label


def traced(label: str, fn, *args):
    """Run ``fn(*args)`` (a worker process's task) under a profile of its own and return ``Traced``: its
    result and every section recorded meanwhile, the task's own under ``label`` and those of its process's
    other threads (a worker's backend start) as they are. The command's process adds them to its table
    with ``untraced``, so ``place3d --profile`` shows where its drive workers spent their time."""
    with profile(print_table=False) as p:
        with section(label):
            value = fn(*args)
    return Traced(value, [(path, p.start + t, sec) for path, kept in p.calls.items() for t, sec in kept], label)


def task(label: str, fn):
    """``fn`` to send to a worker process as it is, or while a profile runs here, ``fn`` under ``traced(label,
    ...)`` (a picklable partial), so that ``untraced`` adds the task's sections to this table."""
    if _ACTIVE is None:
        return fn
    import functools

    return functools.partial(traced, label, fn)


def untraced(result):
    """``result`` itself, or for a ``Traced`` one its value, with its sections added to the profile running
    here (placed by their start; a no-op without a profile), and a row "<task label>: result taken here": from
    the task's end in its process to now (sending the result back, and its wait until this process took it)."""
    if not isinstance(result, Traced):
        return result
    p = _ACTIVE
    if p is not None:
        now = time.perf_counter()
        for path, start, sec in result.calls:
            end = float(start) + float(sec)
            p._add(tuple(path), float(sec), end)
            if tuple(path) == (result.label,):  # the task's own section (``traced``'s label): its hand-over
                p._add((f"{result.label}: result taken here",), max(now - end, 0.0), now)
    return result.value


def _since_start(p: Profile) -> float | None:
    # seconds from interpreter start-up to the profile's start (imports of the package and argparse),
    # where the platform tells the process start time
    try:
        import os

        with open(f"/proc/{_START_PID or os.getpid()}/stat") as f:
            ticks = int(f.read().rsplit(")", 1)[1].split()[19])
        with open("/proc/uptime") as f:
            up = float(f.read().split()[0])
        return max(up - ticks / os.sysconf("SC_CLK_TCK") - (time.perf_counter() - p.start), 0.0)
    except (OSError, ValueError, IndexError, AttributeError):
        return None


def report(p: Profile, before: float | None = None) -> str:
    """The profile table with a header line (and the start-up time before it, if known)."""
    head = "place3d profile (wall seconds; nested rows are part of their parent)"
    if before is not None:
        head += f"\nprocess start-up before the profile (interpreter, first imports): {before:.3f} s"
    return head + "\n" + p.table()

