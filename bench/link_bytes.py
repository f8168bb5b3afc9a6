"""Bytes on the wire per arm update, and the update rate a serial link can carry.

Frames are packed with pymavlink's MAVLink 2 codec exactly as the link sends them (trailing
zero bytes of the payload are truncated by MAVLink 2; signing adds 13 bytes per frame). A serial
byte costs 10 bit times (8N1). Two bounds are printed per baud rate:

* bandwidth: companion→FC bytes per update against the link capacity, minus our 1 Hz HEARTBEAT;
* round trips (ardupilot only): DO_SET_SERVO is sent one joint at a time, each waiting for its
  COMMAND_ACK, so an update needs 6 sequential round trips. The figure counts wire time of
  command + ACK only; flight-controller processing (main loop, typically 2.5 ms at 400 Hz) and
  OS latency come on top, so real rates are lower.

Usage: python -m bench.link_bytes [--baud 57600 115200 921600] [--joints 6]
"""

from __future__ import annotations

import argparse

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_interface.calibration import TABLE2_RANGES_DEG, calibration_from_ranges
from firmware_interface.servo import SERVO_DIALECTS

BITS_PER_BYTE = 10  # 8N1: start + 8 data + stop


def codec(signed: bool) -> mavlink.MAVLink:
    mav = mavlink.MAVLink(None, 1, mavlink.MAV_COMP_ID_ONBOARD_COMPUTER)
    if signed:
        mav.signing.secret_key = bytes(32)
        mav.signing.sign_outgoing = True
        mav.signing.timestamp = 1
    return mav


def update_bytes(dialect: str, joints: int, signed: bool) -> tuple[int, int, int]:
    """(frames, companion→FC bytes, FC→companion ACK bytes) for one update of all joints."""
    ranges = (TABLE2_RANGES_DEG * 3)[:joints]
    calibration = calibration_from_ranges(ranges, outputs=range(9, 9 + joints))
    # A mid-range pose; the PWM values do not change the frame size (floats are 4 bytes).
    pwm = calibration.angles_to_pwm_us([(lo + hi) / 2 for lo, hi in ranges])
    sender = SERVO_DIALECTS[dialect](None, calibration)  # type: ignore[arg-type]
    mav = codec(signed)
    fc = codec(signed)
    fc.srcSystem, fc.srcComponent = 1, 1
    out_bytes = ack_bytes = frames = 0
    for command, params in sender.command_params(pwm):
        out_bytes += len(mav.command_long_encode(1, 1, command, 0, *params).pack(mav))
        ack_bytes += len(fc.command_ack_encode(command, 0, 0, 0, 1, 191).pack(fc))
        frames += 1
    return frames, out_bytes, ack_bytes


def heartbeat_bytes(signed: bool) -> int:
    mav = codec(signed)
    return len(mav.heartbeat_encode(18, 8, 0, 0, 4).pack(mav))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--baud", type=int, nargs="+", default=[57_600, 115_200, 921_600])
    parser.add_argument("--joints", type=int, default=6)
    args = parser.parse_args(argv)
    print(f"Arm update of {args.joints} joints, MAVLink 2, 8N1 serial ({BITS_PER_BYTE} bit/byte)")
    print(
        f"{'dialect':<14}{'signed':<8}{'frames':>7}{'out B':>7}{'ack B':>7}  "
        + "".join(f"{f'{b} baud: bw / rtt Hz':>28}" for b in args.baud)
    )
    for dialect in SERVO_DIALECTS:
        for signed in (False, True):
            frames, out_b, ack_b = update_bytes(dialect, args.joints, signed)
            cells = []
            for baud in args.baud:
                bytes_per_s = baud / BITS_PER_BYTE
                bandwidth_hz = (bytes_per_s - heartbeat_bytes(signed)) / out_b
                round_trip_hz = bytes_per_s / (out_b + ack_b)  # sequential: cmd then ack
                cells.append(f"{bandwidth_hz:>17.1f} / {round_trip_hz:>7.1f}")
            print(
                f"{dialect:<14}{'yes' if signed else 'no':<8}{frames:>7}{out_b:>7}{ack_b:>7}  "
                + "".join(f"{c:>28}" for c in cells)
            )
    print(
        "bw: companion→FC bandwidth bound; rtt: bound from waiting for each ACK "
        "(wire time only, no FC processing)."
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
