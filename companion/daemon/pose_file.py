"""Where the arm's outputs were left: a small file the daemon keeps, for its next start.

After an autopilot reboot the arm's outputs carry no pulses (ArduPilot starts them disabled,
PX4 at its disarmed PWM): nothing the autopilot shows then says where the joints are. A daemon
started then (a restart, a crash, a power cycle of the companion) would take them at the park
pose, and its first step would jump from wherever they really are.

So the daemon writes, whenever it changes, per output the lowest and the highest PWM the
output may hold (the acknowledged pose, a step on its way, what a safety switch holds: see
``ControlCore.outputs_left``), from a thread of its own, atomically (a temporary file renamed),
at most once per control step while the arm moves. A daemon killed mid-motion leaves a file
that holds where the joints are to within that band (one control step while moving). The next
start takes the joints at the middle of the band, and when the band is wider than a PWM step
re-sends that middle first, before the first target's steps (at most half a band from the
truth); until every output has acknowledged a pose, the band stays in the file it writes (a
safety switch may hold the outputs anywhere in it, and a reboot then drops what was stored).
What a readback shows still wins over the file (see ``ControlCore.restore_pose``).

A file that cannot be read or does not match the config (other outputs, a PWM outside an
output's calibrated range, a low above its high) is set aside with a warning; one that cannot
be written is said once and the daemon goes on without it. Nothing is synced to disk: a
kill or a crash of the daemon leaves the file to the kernel, which is what this is for.
"""

from __future__ import annotations

import json
import logging
import os
import threading
from collections.abc import Mapping
from pathlib import Path

from firmware_interface import ArmCalibration

log = logging.getLogger("armbridge")

#: A pose file larger than this is not one of ours.
MAX_BYTES = 4096

#: Per output, the lowest and the highest PWM it may hold.
Left = tuple[dict[int, int], dict[int, int]]


def load(path: str, calibration: ArmCalibration) -> Left | None:
    """Per output, the lowest and highest PWM saved in ``path``, if it is there and matches
    ``calibration`` (a file with ``pwm_us`` alone: each output exactly there)."""
    try:
        with open(path, "rb") as file:
            raw = file.read(MAX_BYTES + 1)
    except FileNotFoundError:
        return None
    except OSError as exc:
        log.warning("pose file %s not read (%s): starting from the park pose", path, exc)
        return None
    try:
        if len(raw) > MAX_BYTES:
            raise ValueError(f"over {MAX_BYTES} bytes")
        data = json.loads(raw)
        if not isinstance(data, dict):
            raise ValueError("not a table")
        pwm = _outputs(data, "pwm_us", calibration)
        low = _outputs(data, "low_us", calibration) if "low_us" in data else pwm
        high = _outputs(data, "high_us", calibration) if "high_us" in data else pwm
        for output in pwm:
            if not low[output] <= pwm[output] <= high[output]:
                raise ValueError(
                    f"output {output}: pwm_us {pwm[output]} outside low_us {low[output]} .. "
                    f"high_us {high[output]}"
                )
    except (ValueError, KeyError, TypeError, RecursionError) as exc:
        log.warning("pose file %s set aside (%s): starting from the park pose", path, exc)
        return None
    return low, high


def _outputs(data: dict[str, object], key: str, calibration: ArmCalibration) -> dict[int, int]:
    saved = data[key]
    if not isinstance(saved, dict):
        raise ValueError(f"{key} is not a table")
    pwm = {int(o): v for o, v in saved.items()}
    if set(pwm) != set(calibration.outputs):
        raise ValueError(
            f"{key}: outputs {sorted(pwm)}, the config's {sorted(calibration.outputs)}"
        )
    for output, value in pwm.items():
        joint = calibration.for_output(output)
        if type(value) is not int or not joint.pwm_min_us <= value <= joint.pwm_max_us:
            raise ValueError(f"{key}: output {output}: {value!r} outside its calibrated range")
    return pwm


def write(path: str, left: Left) -> None:
    """Write ``left`` to ``path`` atomically (raises OSError)."""
    low, high = left
    body = {
        "pwm_us": {str(o): (low[o] + high[o]) // 2 for o in sorted(low)},
        "low_us": {str(o): low[o] for o in sorted(low)},
        "high_us": {str(o): high[o] for o in sorted(high)},
    }
    tmp = Path(f"{path}.tmp")
    tmp.write_text(json.dumps(body))
    os.replace(tmp, path)


class PoseSaver:
    """Writes what it is offered to ``path`` from its own thread, the latest first: offers
    that come while a write is on its way are folded into the next one (one value waits at
    most; the control thread never waits on the disk)."""

    def __init__(self, path: str) -> None:
        self.path = path
        self._cond = threading.Condition()
        self._latest: Left | None = None
        self._written: Left | None = None
        self._closing = False
        self._warned = False
        self._thread = threading.Thread(target=self._run, name="pose-file", daemon=True)
        self._thread.start()

    def offer(self, left: Left | None) -> None:
        """Where the outputs may be now (None: nothing new to say)."""
        if left is None:
            return
        with self._cond:
            self._latest = left
            self._cond.notify()

    def close(self, timeout_s: float = 1.0) -> None:
        """Write what was offered last, then stop the thread."""
        with self._cond:
            self._closing = True
            self._cond.notify()
        self._thread.join(timeout_s)

    def _run(self) -> None:
        while True:
            with self._cond:
                while self._latest == self._written and not self._closing:
                    self._cond.wait()
                left = self._latest
                if left == self._written:
                    return  # closing, nothing left to write
            assert left is not None
            self._save(left)
            self._written = left

    def _save(self, left: Left) -> None:
        try:
            write(self.path, left)
        except OSError as exc:
            if not self._warned:
                self._warned = True
                log.warning(
                    "pose file %s not written (%s): a restart starts from park", self.path, exc
                )


def same_everywhere(left: Left) -> bool:
    """Whether every output's band is a single PWM."""
    low, high = left
    return all(low[o] == high[o] for o in low)


def pose_of(left: Left) -> Mapping[int, int]:
    """Per output, the middle of its band."""
    low, high = left
    return {o: (low[o] + high[o]) // 2 for o in low}
