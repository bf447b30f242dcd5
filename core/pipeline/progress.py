"""Progress and time left: stage timing inside the core, and the time-left model
the UI and the command line show."""
from __future__ import annotations

import time

from ..errors import Cancelled
from .budget import release_free_heap


class Stages:
    """Wall time per stage and the progress callback, in one place."""

    def __init__(self, progress):
        self.progress = progress
        self.times: dict[str, float] = {}
        self._name = None
        self._start = 0.0
        self._moved = 0.0
        self.passes: list[dict] = []

    def start(self, name: str) -> None:
        self.stop()
        release_free_heap()
        self._name = name
        self._start = time.perf_counter()
        self.report(0.0)

    def record_pass(self, name: str, device: str, seconds: float) -> None:
        """One transport pass (a direct-light pass, a gather) for the report."""
        self.passes.append({"pass": name, "device": device, "seconds": round(seconds, 4)})
        release_free_heap()

    def book(self, name: str, seconds: float) -> None:
        """Count ``seconds`` of the running stage as ``name`` (one progress bar, two timings)."""
        self.times[name] = self.times.get(name, 0.0) + seconds
        self._moved += seconds

    def expect(self, name: str, share: float) -> None:
        """Tell the progress callback, if it has an ``expect`` method, that stage ``name``
        will do ``share`` of the work it was planned with (0: none, e.g. a valid cache)."""
        expect = getattr(self.progress, "expect", None)
        if expect is not None:
            expect(name, float(share))

    def note(self, text: str) -> None:
        """Tell the progress callback, if it has a ``note`` method, what the running stage is
        doing in words ('' clears it), e.g. how much the cache stage is about to write."""
        note = getattr(self.progress, "note", None)
        if note is not None:
            note(text)

    def report(self, fraction: float) -> None:
        if self.progress is not None and self._name is not None:
            self.progress(self._name, float(fraction))

    def stop(self) -> None:
        if self._name is not None:
            elapsed = time.perf_counter() - self._start - self._moved
            self.times[self._name] = self.times.get(self._name, 0.0) + elapsed
            self._name = None
            self._moved = 0.0


# The stages of a bake in the order they run, and their rough share of its time (the
# demo: layout and samples a few percent, visibility and transport the rest).
STAGES = (("layout", 0.03), ("unwrap", 0.05), ("samples", 0.03), ("cache", 0.07), ("visibility", 0.42),
          ("transport", 0.38), ("outputs", 0.02))


class Progress:
    """Progress of a running bake, written by the bake (any thread) and read by the UI.

    The callback the core calls raises :class:`Cancelled` once :meth:`cancel` was
    asked for: the core calls it every batch of rays or directions (a fraction of a
    second), so a cancel takes effect within about a second.

    With a :meth:`plan` (the bake's known work), the time left and the percentage come
    from the work still to do at the rates measured so far; the core corrects the plan
    through :meth:`expect` when it learns that a stage has less to do (a valid cache).
    """

    # Rates assumed until the bake has measured its own (this machine, 2 cores: embree
    # 5.4 Mrays/s, the numpy gather ~15 M lookups/s on the demo, docs/benchmarks.md;
    # unwraps are planned in this machine's seconds, layout.unwrap_seconds; samples
    # placed and results written ~1 M/s; the cache ~350 MB/s on disk).
    ASSUMED_RATES = {"unwrap": 1.0, "samples": 1.3e6, "cache": 3.5e8, "visibility": 5e6, "transport": 1.5e7,
                     "outputs": 1e6}

    def __init__(self):
        self.stage = "layout"
        self.fraction = 0.0
        self.started = self.stage_started = time.perf_counter()
        self.cancelled = False
        self.done_share = 0.0  # of the stages finished before the current one (without a plan)
        self.work = None
        self._anchor = None  # (time, fraction) of the running stage's first step
        self._reported_at = self.started
        self._highest_percent = 0
        self.detail = ""  # what the running stage is doing, in words (Stages.note)

    def __call__(self, stage: str, fraction: float) -> None:
        if self.cancelled:
            raise Cancelled()
        stage_changed = stage != self.stage
        if stage_changed:
            order = [name for name, _ in STAGES]
            if stage in order and self.stage in order and order.index(stage) > order.index(self.stage):
                shares = dict(STAGES)
                self.done_share = sum(shares[name] for name in order[:order.index(stage)])
            if self.work is not None and self.stage in self.work:
                # What it did is done; what it did not (the cache stage checks first and
                # writes later) is still to come.
                self._measure()
                self.work[self.stage] *= 1.0 - self.fraction
            self.stage, self.stage_started = stage, time.perf_counter()
            self._anchor = None
            self.detail = ""
        fraction = min(max(float(fraction), 0.0), 1.0)
        if stage_changed or fraction != self.fraction:
            self._reported_at = time.perf_counter()  # progress made (a cancel check is not)
        self.fraction = fraction
        if self._anchor is None and self.fraction > 0.0:
            # Rates are measured from the first step of real work on: a stage's set-up
            # (building the ray scene, reading inputs) is spent once, not per unit.
            self._anchor = (time.perf_counter(), self.fraction)

    def cancel(self) -> None:
        self.cancelled = True

    def note(self, text: str) -> None:
        self.detail = text

    def plan(self, work: dict) -> None:
        """The bake's known work per stage (see ``BakeJob.expected_work``); a stage left out costs nothing."""
        self.work = {name: float(units) for name, units in work.items()}
        self.rates = dict(self.ASSUMED_RATES)

    def expect(self, stage: str, share: float) -> None:
        """Stage ``stage`` will do only ``share`` of its planned work (0: it is skipped)."""
        if self.work is not None and stage in self.work:
            self.work[stage] *= max(0.0, float(share))

    def _measure(self) -> None:
        """The running stage's own rate replaces the assumed one once it has done a few
        percent more than at its first step."""
        if self._anchor is None or self.stage not in self.work or self.work[self.stage] <= 0:
            return
        since, at = self._anchor
        if self.fraction - at >= 0.02:
            elapsed = time.perf_counter() - since
            self.rates[self.stage] = max(self.work[self.stage] * (self.fraction - at) / max(elapsed, 1e-6), 1e-6)

    @property
    def percent(self) -> int:
        left = self.seconds_left()
        if left is None:
            share = dict(STAGES).get(self.stage, 0.0)
            percent = int(100 * min(1.0, self.done_share + share * self.fraction))
        else:
            elapsed = time.perf_counter() - self.started
            percent = int(100 * elapsed / max(elapsed + left, 1e-6)) if left > 0 else 100
        # Never backwards: an estimate that grows should not undo the bar.
        self._highest_percent = max(self._highest_percent, min(percent, 100))
        return self._highest_percent

    def stage_seconds_left(self) -> float | None:
        """Time left in the running stage at its present rate; None before a first estimate."""
        if self.fraction < 0.02:
            return None
        elapsed = time.perf_counter() - self.stage_started
        return elapsed * (1.0 - self.fraction) / self.fraction

    def seconds_left(self) -> float | None:
        """Time left for the whole bake, from the work still to do at the rates seen so far.

        None without a :meth:`plan`.
        """
        if self.work is None:
            return None
        self._measure()
        left = 0.0
        for name, units in self.work.items():
            if name != self.stage:
                left += units / self.rates[name]
            else:
                # Time passes between reports (one large unwrap reports only when done).
                since = time.perf_counter() - self._reported_at
                left += max(units * (1.0 - self.fraction) / self.rates[name] - since, 0.0)
        return left

    def status_text(self) -> str:
        left = self.seconds_left()
        if left is None:
            left = self.stage_seconds_left()
            eta = f", about {left:.0f} s left in this stage" if left is not None else ""
        else:
            eta = f", about {left:.0f} s left"
        detail = f": {self.detail}" if self.detail else ""
        return (f"VisiBake: {self.stage}{detail} {int(100 * self.fraction)}% ({self.percent}% of the bake{eta})"
                " - Esc to cancel")
