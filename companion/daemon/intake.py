"""Where requests wait for the control thread: bounded, newest target wins, stop first.

Every input thread (the MAVLink reader, the control socket) hands its requests to one
:class:`Intake`; the control thread takes them. Nothing here grows with the input:

* **one motion slot** (``goto``, ``trajectory``): a new target replaces a waiting one, and the
  replaced one is answered CANCELLED at once ("superseded"). A flood of targets therefore costs
  one slot and one answer each, never a queue of work;
* **stop, park and resume** wait in a short queue of their own and are taken before any
  target. A stop or park also cancels a waiting target (it was asked for later than the
  target), and a stop a waiting park or resume (the same reason: the last word is the stop).
  The same kind from the same input (a source's first element) asked again while one is
  waiting joins it and gets the same answer;
* **per-source rate limits** (a token bucket per source, ``rate_hz`` with ``burst``): a target
  over the limit is answered TEMPORARILY_REJECTED at once. ``stop``, ``park`` and ``resume``
  are never rate limited (they coalesce instead). At most ``max_sources`` buckets are kept
  (the least recently used one goes);
* **per-input rate limits**: all the sources of one input (``INPUTS``: MAVLink, the control
  socket; a source's first element) share a bucket ``LINK_SHARE`` times as large, so that a sender
  rotating its system ids (unsigned MAVLink ids prove nothing) or opening connection after
  connection cannot multiply the per-source limit;
* after :meth:`close`, every request is answered at once, and so is everything still waiting.

Refusals are logged as a summary (:class:`RefusalLog`): the first one at once, then one line per
``interval_s`` with the counts, so a flood cannot fill the journal.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from collections.abc import Callable, Hashable
from concurrent.futures import Future
from dataclasses import dataclass, field

from companion.daemon.requests import MOTION_KINDS, Outcome, Reply, Request

log = logging.getLogger("armbridge")

Clock = Callable[[], float]
#: How a rate-limited request's answer begins.
RATE_LIMITED = "rate limited"
#: An input's bucket (every source of it together) holds this many sources' rate and burst:
#: two ground stations at their full rate, not a fleet of forged system ids.
LINK_SHARE = 2.0
#: The inputs whose sources share a bucket: those anyone on the link or the machine reaches.
INPUTS = ("mavlink", "socket")


class TokenBucket:
    """``rate_hz`` tokens a second, at most ``burst`` saved up."""

    def __init__(self, rate_hz: float, burst: float, now_s: float) -> None:
        self.rate_hz = rate_hz
        self.burst = burst
        self._tokens = burst
        self._at_s = now_s

    def take(self, now_s: float) -> bool:
        elapsed = max(0.0, now_s - self._at_s)
        self._tokens = min(self.burst, self._tokens + elapsed * self.rate_hz)
        self._at_s = now_s
        if self._tokens >= 1.0:
            self._tokens -= 1.0
            return True
        return False


class RefusalLog:
    """Logs refused requests as a rate-limited summary (thread-safe)."""

    def __init__(self, *, clock: Clock = time.monotonic, interval_s: float = 10.0) -> None:
        self.clock = clock
        self.interval_s = interval_s
        self._lock = threading.Lock()
        self._counts: collections.Counter[str] = collections.Counter()
        self._last_log_s = -float("inf")

    def note(self, kind: str, outcome: Outcome, message: str) -> None:
        now = self.clock()
        with self._lock:
            self._counts[f"{kind} {outcome.value}"] += 1
            if now - self._last_log_s < self.interval_s:
                return
            counts, self._counts = self._counts, collections.Counter()
            self._last_log_s = now
        total = sum(counts.values())
        if total == 1:
            log.info("%s refused (%s): %s", kind, outcome.value, message)
        else:
            summary = ", ".join(f"{n} {what}" for what, n in counts.most_common())
            log.info(
                "%d requests refused since the last report (%s); latest: %s",
                total,
                summary,
                message,
            )


@dataclass(eq=False)
class _Waiting:
    """A stop or park in the queue, with the requests that joined it."""

    request: Request
    followers: list[Request] = field(default_factory=list)


def _answer_followers(followers: list[Request]) -> Callable[[Future[Reply]], None]:
    def answer(future: Future[Reply]) -> None:
        for request in followers:
            request.answer(future.result())

    return answer


class Intake:
    """The requests waiting for the control thread (see the module docstring).

    ``wake`` is set whenever there is something to take.
    """

    def __init__(
        self,
        *,
        clock: Clock = time.monotonic,
        rate_hz: float = 100.0,
        burst: float = 20.0,
        max_sources: int = 256,
        refusals: RefusalLog | None = None,
        wake: threading.Event | None = None,
    ) -> None:
        self.clock = clock
        self.rate_hz = rate_hz
        self.burst = burst
        self.max_sources = max_sources
        self.refusals = refusals or RefusalLog(clock=clock)
        self.wake = wake or threading.Event()
        self._lock = threading.Lock()
        self._motion: Request | None = None
        self._commands: collections.deque[_Waiting] = collections.deque()
        self._buckets: collections.OrderedDict[Hashable, TokenBucket] = collections.OrderedDict()
        self._inputs: dict[Hashable, TokenBucket] = {}
        self._closed: Reply | None = None
        self.counters = {"cancelled": 0, "rate_limited": 0}

    def submit(self, request: Request) -> None:
        """Queue ``request`` or answer it now (closed, rate limited); may answer the target it
        replaces. Never blocks on the control thread."""
        answers: list[tuple[Request, Reply]] = []
        with self._lock:
            if self._closed is not None:
                answers.append((request, self._closed))
            elif request.kind in MOTION_KINDS:
                refusal = self._allow(request.source)
                if refusal is not None:
                    self.counters["rate_limited"] += 1
                    answers.append(
                        (request, Reply(Outcome.TEMPORARILY_REJECTED, f"{RATE_LIMITED}: {refusal}"))
                    )
                else:
                    if self._motion is not None:
                        answers.append(
                            (self._motion, Reply(Outcome.CANCELLED, "superseded by a newer target"))
                        )
                    self._motion = request
            else:
                if self._motion is not None and request.kind != "resume":
                    answers.append(
                        (self._motion, Reply(Outcome.CANCELLED, f"{request.kind} asked after it"))
                    )
                    self._motion = None
                if request.kind == "stop":
                    answers += self._cancel_commands(("park", "resume"))
                same = next(
                    (
                        w
                        for w in self._commands
                        if w.request.kind == request.kind
                        and w.request.direct == request.direct
                        and w.request.origin == request.origin
                    ),
                    None,
                )
                if same is not None:
                    same.followers.append(request)
                else:
                    self._commands.append(_Waiting(request))
        self._answer(answers)
        self.wake.set()

    def take(self) -> list[Request]:
        """Everything waiting, stop/park first; followers are answered with their leader."""
        with self._lock:
            commands, self._commands = list(self._commands), collections.deque()
            motion, self._motion = self._motion, None
        taken = []
        for waiting in commands:
            if waiting.followers:
                waiting.request.future.add_done_callback(_answer_followers(waiting.followers))
            taken.append(waiting.request)
        if motion is not None:
            taken.append(motion)
        for request in taken:
            request.taken.set()
        return taken

    def withdraw(self, request: Request) -> bool:
        """Take ``request`` back if it is still waiting (its caller gave up); True if it was.
        The caller answers it."""
        with self._lock:
            if self._motion is request:
                self._motion = None
                return True
            for waiting in self._commands:
                if waiting.request is request:
                    if waiting.followers:
                        waiting.request = waiting.followers.pop(0)
                    else:
                        self._commands.remove(waiting)
                    return True
                if request in waiting.followers:
                    waiting.followers.remove(request)
                    return True
        return False

    def close(self, reply: Reply, waiting: Reply) -> None:
        """Refuse everything from now on with ``reply``; answer what waits with ``waiting``."""
        with self._lock:
            self._closed = reply
            queued = [r for w in self._commands for r in (w.request, *w.followers)]
            if self._motion is not None:
                queued.append(self._motion)
            self._commands.clear()
            self._motion = None
        self._answer([(r, waiting) for r in queued])
        self.wake.set()

    def _cancel_commands(self, kinds: tuple[str, ...]) -> list[tuple[Request, Reply]]:
        """Take the waiting commands of ``kinds`` out (a stop asked after them): their
        answers (call with the lock held)."""
        cancelled = [w for w in self._commands if w.request.kind in kinds]
        answers = []
        for waiting in cancelled:
            self._commands.remove(waiting)
            reply = Reply(Outcome.CANCELLED, "stop asked after it")
            answers += [(r, reply) for r in (waiting.request, *waiting.followers)]
        return answers

    def _allow(self, source: Hashable) -> str | None:
        """None if a target from ``source`` may go on, else which limit it is over."""
        now = self.clock()
        bucket = self._buckets.get(source)
        if bucket is None:
            bucket = TokenBucket(self.rate_hz, self.burst, now)
            self._buckets[source] = bucket
            if len(self._buckets) > self.max_sources:
                self._buckets.popitem(last=False)
        else:
            self._buckets.move_to_end(source)
        if not bucket.take(now):
            return f"at most {self.rate_hz:g} targets/s per source"
        kind = source[0] if isinstance(source, tuple) and source else source
        if kind not in INPUTS:
            return None
        shared = self._inputs.get(kind)
        if shared is None:
            shared = self._inputs[kind] = TokenBucket(
                self.rate_hz * LINK_SHARE, self.burst * LINK_SHARE, now
            )
        if not shared.take(now):
            return f"at most {self.rate_hz * LINK_SHARE:g} targets/s from all {kind} sources"
        return None

    def _answer(self, answers: list[tuple[Request, Reply]]) -> None:
        for request, reply in answers:
            request.taken.set()
            if request.answer(reply):
                if reply.outcome is Outcome.CANCELLED:
                    with self._lock:
                        self.counters["cancelled"] += 1
                self.refusals.note(request.kind, reply.outcome, reply.message)
