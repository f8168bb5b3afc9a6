"""Where the arm's outputs were left: a small file the daemon keeps, for its next start.

After an autopilot reboot the arm's outputs carry no pulses (ArduPilot starts them disabled,
PX4 at its disarmed PWM): nothing the autopilot shows then says where the joints are. A daemon
started then (a restart, a crash, a power cycle of the companion) would take them at the park
pose, and its first step would jump from wherever they really are. So the daemon writes the
PWMs its outputs acknowledged whenever the arm comes to rest (at most once a second, from the
main thread, atomically: a temporary file renamed), and reads them at its start; what a
readback shows still wins over them (see ``core.ControlCore.restore_pose``).

A file that cannot be read or does not match the config (other outputs, a PWM outside an
output's calibrated range) is set aside with a warning; one that cannot be written is said
once and the daemon goes on without it.
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Mapping
from pathlib import Path

from firmware_interface import ArmCalibration

log = logging.getLogger("armbridge")

#: The file is written at most this often while the arm comes to rest now and then.
SAVE_INTERVAL_S = 1.0
#: A pose file larger than this is not one of ours.
MAX_BYTES = 4096


def load(path: str, calibration: ArmCalibration) -> dict[int, int] | None:
    """The PWM per output saved in ``path``, if it is there and matches ``calibration``."""
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
        saved = data["pwm_us"]
        if not isinstance(saved, dict):
            raise ValueError("pwm_us is not a table")
        pwm = {int(o): v for o, v in saved.items()}
        if set(pwm) != set(calibration.outputs):
            raise ValueError(f"outputs {sorted(pwm)}, the config's {sorted(calibration.outputs)}")
        for output, value in pwm.items():
            joint = calibration.for_output(output)
            if type(value) is not int or not joint.pwm_min_us <= value <= joint.pwm_max_us:
                raise ValueError(f"output {output}: {value!r} outside its calibrated range")
    except (ValueError, KeyError, TypeError, RecursionError) as exc:
        log.warning("pose file %s set aside (%s): starting from the park pose", path, exc)
        return None
    return pwm


class PoseSaver:
    """Writes the outputs' PWMs to ``path`` when they changed and the arm is at rest."""

    def __init__(self, path: str, clock_s: float) -> None:
        self.path = path
        self._saved: dict[int, int] | None = None
        self._saved_s = clock_s - SAVE_INTERVAL_S
        self._warned = False

    def offer(self, pwm_by_output: Mapping[int, int] | None, now_s: float) -> None:
        """The outputs' PWMs with the arm at rest (None: moving, or not all known)."""
        if pwm_by_output is None or dict(pwm_by_output) == self._saved:
            return
        if now_s - self._saved_s < SAVE_INTERVAL_S:
            return
        self.save(pwm_by_output, now_s)

    def save(self, pwm_by_output: Mapping[int, int], now_s: float) -> None:
        pwm = dict(pwm_by_output)
        tmp = Path(f"{self.path}.tmp")
        try:
            tmp.write_text(json.dumps({"pwm_us": {str(o): v for o, v in sorted(pwm.items())}}))
            os.replace(tmp, self.path)
        except OSError as exc:
            if not self._warned:
                self._warned = True
                log.warning(
                    "pose file %s not written (%s): a restart starts from park", self.path, exc
                )
            return
        self._saved, self._saved_s = pwm, now_s
