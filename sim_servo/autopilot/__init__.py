"""The simulated autopilot's MAVLink behaviour: bytes in, frames out, given the time.

:class:`SimAutopilot` (:mod:`sim_servo.autopilot.dispatcher`) composes the parts; see there for
the map of where each behaviour lives.
"""

from sim_servo.autopilot.dispatcher import SimAutopilot
from sim_servo.autopilot.flavour import px4_actuator_pwm_us
from sim_servo.autopilot.outputs import PX4_FORCE_MAGIC
from sim_servo.autopilot.wire import SIGNING_EPOCH_UNIX_S

__all__ = ["PX4_FORCE_MAGIC", "SIGNING_EPOCH_UNIX_S", "SimAutopilot", "px4_actuator_pwm_us"]
