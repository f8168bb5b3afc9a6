"""The outputs' truth: what the autopilot's outputs really do (an ACK proves nothing).

One interface, :class:`OutputsTruth`, and one class per firmware: PX4's readback
(:mod:`.outputs_px4`) and ArduPilot's safety switch (:mod:`.outputs_ardupilot`). The rest of
the core asks it ("may the motion go on?", "may I step to this pose?", "what is dead?", "what
is unknown for status?", "a loss happened", "a readback came") and never asks which firmware
it talks to.
"""

from __future__ import annotations

import abc
import math
from collections.abc import Sequence
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from companion.daemon.core.actions import Action
    from companion.daemon.core.dispatcher import ControlCore
    from companion.daemon.core.state import Flight

#: A band of poses: per joint, the lowest and the highest angle.
Band = tuple[list[float], list[float]]


def band_of(poses: Sequence[Sequence[float]]) -> Band:
    """Per joint, the lowest and the highest angle of ``poses``."""
    return (
        [min(p[i] for p in poses) for i in range(len(poses[0]))],
        [max(p[i] for p in poses) for i in range(len(poses[0]))],
    )


def middle(band: Band) -> tuple[float, ...]:
    """Per joint, the middle of a band (within half its width of every angle in it)."""
    return tuple((lo + hi) / 2 for lo, hi in zip(*band, strict=True))


class OutputsTruth(abc.ABC):
    """What one firmware says of its outputs, and what the motion may do about it."""

    def __init__(self, core: ControlCore) -> None:
        self._core = core
        #: The last SERVO_OUTPUT_RAW: output → PWM shown, and when it arrived.
        self.shown: dict[int, int] = {}
        self.shown_s = -math.inf
        #: The safety switch by the last SYS_STATUS (None: none since the start, a loss or a
        #: reboot); shown in status.
        self.safety_on: bool | None = None

    # -- frames -----------------------------------------------------------------------------

    def on_readback(self, shown: dict[int, int], received_s: float) -> None:
        """A SERVO_OUTPUT_RAW showing ``shown`` (output → PWM), arrived at ``received_s``."""
        self.shown = shown
        # When it arrived (the control thread may take it later): the readback's silence
        # is the link's, not this thread's.
        self.shown_s = received_s
        self._check_readback()

    def _check_readback(self) -> None:  # noqa: B027
        """What the readback just shown says of the outputs (default: nothing)."""

    @abc.abstractmethod
    def on_sys_status(self, actions: list[Action], safety_on: bool) -> None:
        """A SYS_STATUS saying where the safety switch is."""

    def on_param(self, name: str, value: float) -> None:  # noqa: B027
        """A PARAM_VALUE from the pinned autopilot (default: none is read)."""

    def params_to_read(self) -> list[str]:
        """Parameters to read whenever the streams are asked for (default: none)."""
        return []

    def streams_asked(self, now: float) -> None:  # noqa: B027
        """Every stream was just asked for."""

    def rebooted(self) -> None:  # noqa: B027
        """The autopilot rebooted (before :meth:`lost`)."""

    # -- losses -----------------------------------------------------------------------------

    @abc.abstractmethod
    def lost(self, flights: Sequence[Flight]) -> None:
        """The link was lost or the autopilot rebooted; ``flights`` (no longer tracked) were on
        their way. Forget what the outputs were known to do, and set the pose to re-send."""

    @abc.abstractmethod
    def went_quiet(self, flights: Sequence[Flight], now: float) -> None:
        """SYSTEM_TIME stopped (a possible reboot); ``flights`` are still on their way."""

    # -- the motion's questions --------------------------------------------------------------

    def take_hold(self) -> bool:
        """Whether the outputs must be told to hold the acknowledged pose now, before anything
        else (asked once: True clears it)."""
        return False

    @property
    def hold_wanted(self) -> bool:
        """:meth:`take_hold` would say True."""
        return False

    @abc.abstractmethod
    def may_move(self, actions: list[Action], now: float) -> bool:
        """Whether the next update may go out (nothing in flight); may send one itself."""

    def may_pipeline(self) -> bool:
        """Whether a step may go out behind the update in flight (outputs known live)."""
        return True

    def may_step_to(self, step: tuple[float, ...]) -> bool:
        """Whether a motion step to ``step`` may go out now."""
        return True

    def stepped_to(self, step: tuple[float, ...]) -> None:  # noqa: B027
        """An update to ``step`` went out."""

    def acknowledged(self, output: int, pwm: int, now: float) -> None:  # noqa: B027
        """``output`` acknowledged ``pwm`` at ``now``."""

    def all_acknowledged(self) -> None:  # noqa: B027
        """Every output holds what it acknowledged."""

    def overtaken(self, seq: int) -> set[int]:
        """Outputs whose ACKs in the update numbered ``seq`` say nothing of their pose (a
        hold was stored behind it)."""
        return set()

    @abc.abstractmethod
    def dead(self) -> dict[int, str]:
        """The arm's outputs that are not live now, with the reason."""

    @abc.abstractmethod
    def unknown(self, now: float) -> dict[int, str]:
        """For status, the arm's outputs not known to be live, with the reason."""

    @abc.abstractmethod
    def streams_silent(self, now: float) -> bool:
        """Whether the stream this firmware's truth comes from fell silent long enough to ask
        for every stream again (logged)."""

    @abc.abstractmethod
    def refusal_advice(self, refused: dict[int, str]) -> tuple[str, str]:
        """What to do about refused outputs: (a hint for the log and reply, a short line)."""
