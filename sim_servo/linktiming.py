"""When the autopilot's frames leave one link: the delay-and-hold model fitted to ArduCopter SITL.

:class:`LinkOutput` is one link's outgoing side, pure (times are given, nothing is read from a
clock): the autopilot :meth:`~LinkOutput.write`\\ s the frames it produces, tells it when whole
frames :meth:`~LinkOutput.arrived` from that link, and :meth:`~LinkOutput.take`\\ s the frames
that leave by a time. The model and the figures it was fitted to are in
:class:`sim_servo.config.LinkTimingConfig`; in short, with ``d = output_delay_ms``,
``H = hold_ms`` and ``N = burst_frames``:

1. a frame produced at ``t`` is ready at ``t + d`` (plus the latency fault, if any);
2. a ready frame is held; everything held leaves at once when

   * a frame arrives from the link (the next frame flushes, as a TCP segment carries the
     peer's pending ACK), or
   * the link's *window* closes: ``H`` after the frame that opened it; with no window open,
     ``H`` after the first held frame was ready, or
   * ``N`` or more frames arrived within the open window (TCP acknowledges at least every
     second segment at once); then every frame that becomes ready in that window leaves at once.

   A frame arriving with no window open opens one; so does a frame arriving after something
   left during the open window (that output answered the window's frames; the new frame waits
   for its own answer).

``H = 0`` turns the hold off, ``d = 0`` the delay: :meth:`LinkTimingConfig.instant`.
"""

from __future__ import annotations

import heapq
import itertools
import math

from sim_servo.config import LinkTimingConfig


class LinkOutput:
    """One link's outgoing frames under :class:`LinkTimingConfig`."""

    def __init__(self, config: LinkTimingConfig) -> None:
        self.config = config
        self._delay_s = config.output_delay_ms / 1000.0
        self._hold_s = config.hold_ms / 1000.0
        self._seq = itertools.count()
        #: (ready_s, order, frame): produced, not yet through the output delay.
        self._delayed: list[tuple[float, int, bytes]] = []
        self._held: list[bytes] = []
        self._held_since_s: float | None = None
        #: The frame that opened the window arrived then (None: closed); frames since; whether
        #: anything left since it opened.
        self._window_start_s: float | None = None
        self._window_frames = 0
        self._window_answered = False
        self._released: list[bytes] = []
        self._released_s: float | None = None

    def write(self, frame: bytes, now_s: float, extra_delay_s: float = 0.0) -> None:
        """A frame produced at ``now_s``; ``extra_delay_s`` is added (the latency fault)."""
        ready_s = now_s + max(0.0, extra_delay_s) + self._delay_s
        heapq.heappush(self._delayed, (ready_s, next(self._seq), frame))

    def arrived(self, frames: int, now_s: float) -> None:
        """``frames`` whole frames arrived from this link at ``now_s``."""
        self._advance(now_s)
        if frames <= 0:
            return
        if self._held:
            self._flush(now_s)
        if self._window_start_s is None or self._window_answered:
            self._window_start_s, self._window_frames, self._window_answered = now_s, 0, False
        self._window_frames += frames
        if self._hold_s == 0.0:
            self._close_window()

    def take(self, now_s: float) -> list[bytes]:
        """The frames that leave by ``now_s``, in the order they were written."""
        self._advance(now_s)
        frames, self._released, self._released_s = self._released, [], None
        return frames

    def next_event_s(self) -> float | None:
        """When :meth:`take` next has frames to give (None: nothing pending)."""
        candidates = []
        if self._released_s is not None:
            candidates.append(self._released_s)
        if self._delayed:
            candidates.append(self._delayed[0][0])
        if self._held:
            candidates.append(self._held_deadline_s())
        return min(candidates) if candidates else None

    def clear(self) -> None:
        """Forget every frame not yet gone and the window (the autopilot rebooted)."""
        self._delayed.clear()
        self._held.clear()
        self._released.clear()
        self._held_since_s = self._released_s = None
        self._close_window()

    @property
    def pending(self) -> int:
        """Frames produced that have not left yet."""
        return len(self._delayed) + len(self._held) + len(self._released)

    # -- the model ---------------------------------------------------------------------------

    def _window_end_s(self) -> float | None:
        return None if self._window_start_s is None else self._window_start_s + self._hold_s

    def _held_deadline_s(self) -> float:
        end_s = self._window_end_s()
        if end_s is not None:
            return end_s
        assert self._held_since_s is not None  # something is held
        return self._held_since_s + self._hold_s

    def _advance(self, now_s: float) -> None:
        """Apply, in time order, every readiness and every window or hold deadline ≤ ``now_s``."""
        while True:
            ready_s = self._delayed[0][0] if self._delayed else None
            end_s = self._window_end_s()
            deadline_s = self._held_deadline_s() if self._held else None
            # A frame ready exactly when a window closes is released with it.
            if ready_s is not None and ready_s <= now_s and (end_s is None or ready_s <= end_s):
                if deadline_s is not None and deadline_s < ready_s:
                    self._flush(deadline_s)
                    continue
                _, _, frame = heapq.heappop(self._delayed)
                self._hold(frame, ready_s)
            elif end_s is not None and end_s <= now_s:
                if self._held:
                    self._flush(end_s)
                self._close_window()
            elif deadline_s is not None and deadline_s <= now_s:
                self._flush(deadline_s)
            else:
                return

    def _hold(self, frame: bytes, ready_s: float) -> None:
        if not self._held:
            self._held_since_s = ready_s
        self._held.append(frame)
        if self._hold_s == 0.0 or self._window_frames >= self.config.burst_frames:
            self._flush(ready_s)

    def _flush(self, at_s: float) -> None:
        if self._window_start_s is not None:
            self._window_answered = True
        self._released.extend(self._held)
        self._held.clear()
        self._held_since_s = None
        if self._released_s is None:
            self._released_s = at_s

    def _close_window(self) -> None:
        self._window_start_s, self._window_frames, self._window_answered = None, 0, False


class LoopLinkOutput:
    """One link's outgoing frames in the PX4 flavour (:class:`~sim_servo.config.Px4TimingConfig`):
    a frame produced at ``t`` (plus any extra delay: the latency fault, a forwarding delay)
    leaves on the link's first MAVLink main-loop pass at or after it, passes every ``loop_s``
    from ``phase_s`` (the boot). ``loop_s`` 0: at once. Same interface as :class:`LinkOutput`."""

    def __init__(self, loop_s: float, phase_s: float) -> None:
        if not loop_s >= 0.0:
            raise ValueError(f"loop_s={loop_s!r} must be >= 0")
        self._loop_s = loop_s
        self.phase_s = phase_s
        self._seq = itertools.count()
        self._queue: list[tuple[float, int, bytes]] = []

    def _pass_s(self, ready_s: float) -> float:
        if self._loop_s == 0.0:
            return ready_s
        passes = math.ceil(round((ready_s - self.phase_s) / self._loop_s, 9))
        return self.phase_s + passes * self._loop_s

    def write(self, frame: bytes, now_s: float, extra_delay_s: float = 0.0) -> None:
        leave_s = self._pass_s(now_s + max(0.0, extra_delay_s))
        heapq.heappush(self._queue, (leave_s, next(self._seq), frame))

    def arrived(self, frames: int, now_s: float) -> None:
        """Incoming frames change nothing here."""

    def take(self, now_s: float) -> list[bytes]:
        frames = []
        while self._queue and self._queue[0][0] <= now_s:
            frames.append(heapq.heappop(self._queue)[2])
        return frames

    def next_event_s(self) -> float | None:
        return self._queue[0][0] if self._queue else None

    def clear(self) -> None:
        self._queue.clear()

    @property
    def pending(self) -> int:
        return len(self._queue)
