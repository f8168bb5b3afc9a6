"""A simulated flight controller with simulated servos, for hardware-free tests of the bridge.

``python -m sim_servo --udp 127.0.0.1:14550`` serves MAVLink 2 like ArduCopter (or PX4) would,
moves a slew-limited servo model per output and computes the arm's hand pose from the servo
positions through its own servo model (PWM → joint angle, independent of the daemon's
calibration, which the tests check against it) and the arm's forward kinematics.

Layout (one concern per module):

* :mod:`sim_servo.config`    – settings, output function table, TOML file, validation
* :mod:`sim_servo.servo`     – one servo's position over time (slew, deadband), pure
* :mod:`sim_servo.hand`      – servo positions → joint angles (servo model) → hand pose (FK)
* :mod:`sim_servo.hover`     – the vehicle's seeded hover motion in LOCAL_NED, pure
* :mod:`sim_servo.world`     – vehicle ∘ mount ∘ hand: the hand in LOCAL_NED, pure
* :mod:`sim_servo.faults`    – seeded drop / corrupt / latency decisions
* :mod:`sim_servo.autopilot` – the MAVLink behaviour: bytes in, frames out, given the time
* :mod:`sim_servo.linktiming` – when a link's frames leave (ArduPilot: delay and hold; PX4:
  main-loop passes; both fitted to SITL), pure
* :mod:`sim_servo.endpoints` – UDP / TCP / pty byte endpoints (the server side)
* :mod:`sim_servo.query`     – the local Unix-socket state query
* :mod:`sim_servo.eventlog`  – JSON-lines event log
* :mod:`sim_servo.server`    – the I/O loop tying them together
* :mod:`sim_servo.__main__`  – the command line
"""
