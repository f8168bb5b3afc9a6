"""The shipped Lua bridge script, run by a real Lua 5.3 interpreter (ArduPilot's version, from
lupa) against COMMAND_LONG frames encoded by pymavlink and laid out as ``mavlink_message_t``,
the way ``mavlink:receive_chan()`` returns them, with stand-ins for the bindings it uses
(``mavlink``, ``param``, ``SRV_Channels``, ``gcs``, ``millis``)."""

from __future__ import annotations

import math
import struct
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_interface.lua_bridge import MAV_CMD_USER_2, script_path, script_text

lupa = pytest.importorskip("lupa")
try:
    from lupa import lua53 as lua_impl  # ArduPilot embeds Lua 5.3
except ImportError:  # pragma: no cover - a lupa build without 5.3
    lua_impl = lupa

MSG_T_PAYLOAD_BYTES = 264  # uint64_t payload64[33]
SIGNATURE_BYTES = 13
AUTOPILOT = (1, 1)
#: armbridge's default ids: the vehicle's system id, MAV_COMP_ID_ONBOARD_COMPUTER.
COMPANION = (1, 191)
GCS = (255, 190)

# The bindings as ArduPilot offers them to a script, recording what the script did.
STAND_INS = b"""
local env = {queue = {}, sent = {}, texts = {}, set = {}, params = {}, registered = {},
             blocked = {}, init = nil, tables = {}, add_table_ok = true, now_ms = 0}
mavlink = {}
function mavlink:init(a, b) env.init = {a, b} end
function mavlink:register_rx_msgid(id) env.registered[#env.registered + 1] = id; return true end
function mavlink:block_command(id) env.blocked[#env.blocked + 1] = id; return true end
function mavlink:receive_chan()
  local item = table.remove(env.queue, 1)
  if item then return item[1], item[2], 0 end
end
function mavlink:send_chan(chan, msgid, payload)
  assert(math.type(chan) == "integer" and math.type(msgid) == "integer")
  env.sent[#env.sent + 1] = {chan, msgid, payload}
  return true
end
param = {}
function param:get(name) return env.params[name] end
function param:add_table(key, prefix, count)
  assert(math.type(key) == "integer" and key >= 0 and key <= 200, "key")
  assert(math.type(count) == "integer" and count >= 1 and count <= 63, "count")
  if not env.add_table_ok then return false end
  env.tables[key] = {prefix = prefix, count = count}
  return true
end
function param:add_param(key, index, name, default)
  local t = env.tables[key]
  if t == nil or index < 1 or index > t.count then return false end
  local full = t.prefix .. name
  assert(#full <= 16, "name")
  -- a value stored before (a set, an earlier start) is kept; else the default
  if env.params[full] == nil then env.params[full] = default + 0.0 end
  return true
end
-- millis() is a uint32_t userdata; the script reads it with :toint()
function millis() return {toint = function(self) return env.now_ms end} end
SRV_Channels = {}
function SRV_Channels:set_output_pwm_chan(chan, pwm)
  -- the binding takes integers (get_uint8_t / get_uint16_t)
  assert(math.type(chan) == "integer" and chan >= 0 and chan < 32, "chan")
  assert(math.type(pwm) == "integer" and pwm >= 0 and pwm <= 65535, "pwm")
  env.set[#env.set + 1] = {chan, pwm}
end
gcs = {}
function gcs:send_text(severity, text) env.texts[#env.texts + 1] = text end
return env
"""


def as_mavlink_message_t(wire: bytes, *, past_len: int = 0) -> bytes:
    """A MAVLink 2 frame as the C ``mavlink_message_t`` (packed): checksum, the header from the
    magic byte to the 24-bit msgid, the payload in its 264-byte area (``past_len`` fills the
    bytes after ``len``, which a reader must not trust), ck[2], signature[13]."""
    assert wire[0] == 0xFD
    length = wire[1]
    payload = wire[10 : 10 + length]
    crc = wire[10 + length : 12 + length]
    area = payload + bytes([past_len]) * (MSG_T_PAYLOAD_BYTES - length)
    return crc + wire[:10] + area + crc + bytes(SIGNATURE_BYTES)


def command_long(
    params: tuple[float, ...],
    *,
    command: int = MAV_CMD_USER_2,
    target: tuple[int, int] = AUTOPILOT,
    sender: tuple[int, int] = COMPANION,
) -> bytes:
    enc = mavlink.MAVLink(None, srcSystem=sender[0], srcComponent=sender[1])
    msg = enc.command_long_encode(target[0], target[1], command, 0, *params)
    return bytes(msg.pack(enc))


def user2(pwms: list[float], first: int, **kw: Any) -> bytes:
    slots = [*pwms, *[math.nan] * (6 - len(pwms))]
    return as_mavlink_message_t(command_long((*slots, float(first)), **kw))


class Bridge:
    """The script loaded once, as ArduPilot runs it: its top level, then ``update`` per loop."""

    def __init__(
        self,
        functions: dict[int, int] | None = None,
        sysid: int = 1,
        *,
        stored: dict[str, float] | None = None,
        add_table_ok: bool = True,
    ) -> None:
        self.lua = lua_impl.LuaRuntime(encoding=None, unpack_returned_tuples=True)
        self.env = self.lua.execute(STAND_INS)
        self.env.add_table_ok = add_table_ok
        params = self.env.params
        params[b"MAV_SYSID"] = float(sysid)
        for name, value in (stored or {}).items():  # kept in storage from before this start
            params[name.encode()] = float(value)
        for output in range(1, 17):
            params[f"SERVO{output}_FUNCTION".encode()] = float((functions or {}).get(output, 0))
            params[f"SERVO{output}_MIN".encode()] = 1000.0
            params[f"SERVO{output}_MAX".encode()] = 2000.0
        chunk = self.lua.eval("function(src, name) return assert(load(src, name)) end")(
            script_text().encode(), b"=armbridge_servo"
        )
        started = chunk()
        self.update = started[0] if isinstance(started, tuple) else started

    def feed(self, *frames: bytes, chan: int = 1) -> None:
        for frame in frames:
            self.env.queue[len(self.env.queue) + 1] = self.lua.table(frame, chan)
        result = self.update()
        assert result[1] == 5  # the script asks to run again (every LOOP_MS)
        self.update = result[0]

    def param(self, name: str, value: float) -> None:
        """A parameter set (by a ground station) while the script runs."""
        self.env.params[name.encode()] = float(value)

    @property
    def set(self) -> list[tuple[int, int]]:
        return [(s[1], s[2]) for s in self.env.set.values()]

    @property
    def texts(self) -> list[str]:
        return [t.decode() for t in self.env.texts.values()]

    def acks(self) -> list[tuple[int, dict[str, int]]]:
        out = []
        for chan, msgid, payload in (tuple(s.values()) for s in self.env.sent.values()):
            assert msgid == mavlink.MAVLINK_MSG_ID_COMMAND_ACK
            cls = mavlink.MAVLink_command_ack_message
            values = cls.unpacker.unpack(payload)  # pymavlink's own wire layout
            out.append((chan, dict(zip(cls.ordered_fieldnames, values, strict=True))))
        return out


def test_script_ships_with_the_package():
    assert script_path().name == "armbridge_servo.lua"
    assert script_path().is_file()


def test_start_registers_for_command_long_and_blocks_user_2():
    bridge = Bridge()
    assert list(bridge.env.registered.values()) == [mavlink.MAVLINK_MSG_ID_COMMAND_LONG]
    assert list(bridge.env.blocked.values()) == [MAV_CMD_USER_2]
    assert any("v2 ready" in t for t in bridge.texts)


def test_good_update_sets_six_outputs_and_answers_one_accepted_ack():
    bridge = Bridge()
    bridge.feed(user2([1100, 1200, 1300, 1400, 1500, 1600], first=9))
    assert bridge.set == [(8, 1100), (9, 1200), (10, 1300), (11, 1400), (12, 1500), (13, 1600)]
    [(chan, ack)] = bridge.acks()
    assert chan == 1
    assert ack["command"] == MAV_CMD_USER_2
    assert ack["result"] == mavlink.MAV_RESULT_ACCEPTED
    assert (ack["target_system"], ack["target_component"]) == COMPANION


def test_nan_slots_leave_their_outputs_alone():
    bridge = Bridge()
    bridge.feed(user2([1100, math.nan, 1300], first=3))
    assert bridge.set == [(2, 1100), (4, 1300)]
    assert bridge.acks()[0][1]["result"] == mavlink.MAV_RESULT_ACCEPTED


def test_motor_output_refused_and_nothing_set():
    bridge = Bridge(functions={12: 33})  # SERVO12 drives motor 1
    bridge.feed(user2([1100, 1200, 1300, 1400, 1500, 1600], first=9))
    assert bridge.set == []
    [(_, ack)] = bridge.acks()
    assert ack["result"] == mavlink.MAV_RESULT_FAILED
    assert ack["result_param2"] == 12
    assert any("Channel 12 is already in use" in t for t in bridge.texts)


@pytest.mark.parametrize("function", [1, -1, 94])  # RC pass-through, GPIO, Script1
def test_only_disabled_outputs_are_driven(function):
    bridge = Bridge(functions={10: function})
    bridge.feed(user2([1500, 1500], first=9))
    assert bridge.set == []
    assert bridge.acks()[0][1]["result_param2"] == 10


@pytest.mark.parametrize("pwm", [999.0, 2001.0, 1500.5, math.inf, -1500.0])
def test_pwm_outside_servo_range_or_not_integer_refused(pwm):
    bridge = Bridge()
    bridge.feed(user2([1500, 1500, pwm], first=9))
    assert bridge.set == []
    [(_, ack)] = bridge.acks()
    assert (ack["result"], ack["result_param2"]) == (mavlink.MAV_RESULT_FAILED, 11)


@pytest.mark.parametrize("first", [0.0, 1.5, 33.0, math.nan])
def test_bad_first_output_refused_naming_no_output(first):
    bridge = Bridge()
    bridge.feed(user2([1500, 1500, 1500, 1500], first=first))  # type: ignore[arg-type]
    assert bridge.set == []
    [(_, ack)] = bridge.acks()
    assert (ack["result"], ack["result_param2"]) == (mavlink.MAV_RESULT_FAILED, 0)


def test_output_the_board_lacks_refused_naming_it():
    bridge = Bridge()  # SERVO1..16 only, as on a 16-output board
    bridge.feed(user2([1500, 1500, 1500], first=15))
    assert bridge.set == []
    assert bridge.acks()[0][1]["result_param2"] == 17


def test_no_pwm_at_all_refused():
    bridge = Bridge()
    bridge.feed(user2([], first=9))
    assert bridge.set == [] and bridge.acks()[0][1]["result"] == mavlink.MAV_RESULT_FAILED


def test_short_or_other_layout_frames_ignored_and_reported_once():
    bridge = Bridge()
    good = user2([1500], first=9)
    bridge.feed(good[:40], good + b"\0\0\0\0")  # too short; a bigger (32-bit sysid) layout
    assert bridge.set == [] and bridge.acks() == []
    assert sum("unsupported" in t for t in bridge.texts) == 1


def test_bad_magic_or_oversized_payload_ignored():
    bridge = Bridge()
    good = bytearray(user2([1500], first=9))
    bad_magic = bytes(good[:2]) + b"\x55" + bytes(good[3:])
    too_long = bytes(good[:3]) + bytes([34]) + bytes(good[4:])
    bridge.feed(bad_magic, too_long)
    assert bridge.set == [] and bridge.acks() == []


def test_truncated_payload_restored_from_len_not_read_past_it():
    # target_component 0 and confirmation 0 are trailing zeros: MAVLink 2 drops them (len 31).
    wire = command_long((1500.0, *[math.nan] * 5, 9.0), target=(1, 0))
    assert wire[1] < 33
    bridge = Bridge()
    bridge.feed(as_mavlink_message_t(wire, past_len=0xFF))  # 0xFF would read as component 255
    assert bridge.set == [(8, 1500)]


def test_other_commands_and_other_targets_passed_over():
    bridge = Bridge()
    bridge.feed(
        user2([1500], first=9, command=mavlink.MAV_CMD_DO_SET_SERVO),
        user2([1500], first=9, target=(2, 1)),  # another vehicle
        user2([1500], first=9, target=(1, 100)),  # a camera on ours
        as_mavlink_message_t(
            bytes(
                mavlink.MAVLink(None, 255, 190)
                .heartbeat_encode(6, 8, 0, 0, 0)
                .pack(mavlink.MAVLink(None, 255, 190))
            )
        ),
    )
    assert bridge.set == [] and bridge.acks() == []


DENIED_TEXT = "armbridge: denied 255/190: not ARMB_SYSID/COMPID"


def test_start_adds_the_companion_parameters_at_armbridges_defaults():
    bridge = Bridge()
    table = bridge.env.tables[143]
    assert (table.prefix, table.count) == (b"ARMB_", 2)
    assert bridge.env.params[b"ARMB_SYSID"] == 0.0  # 0: the autopilot's own system id
    assert bridge.env.params[b"ARMB_COMPID"] == 191.0
    kept = Bridge(stored={"ARMB_SYSID": 42, "ARMB_COMPID": 200})  # set before a reboot
    assert (kept.env.params[b"ARMB_SYSID"], kept.env.params[b"ARMB_COMPID"]) == (42.0, 200.0)


@pytest.mark.parametrize("sender", [GCS, (1, 190), (2, 191), (1, 1)])
def test_a_foreign_sender_is_denied_and_nothing_is_set(sender):
    bridge = Bridge()
    bridge.feed(user2([1100, 1200, 1300, 1400, 1500, 1600], first=9, sender=sender))
    assert bridge.set == []
    [(chan, ack)] = bridge.acks()
    assert chan == 1
    assert (ack["command"], ack["result"], ack["result_param2"]) == (
        MAV_CMD_USER_2,
        mavlink.MAV_RESULT_DENIED,
        0,
    )
    assert (ack["target_system"], ack["target_component"]) == sender
    said = f"armbridge: denied {sender[0]}/{sender[1]}: not ARMB_SYSID/COMPID"
    assert bridge.texts[-1] == said


def test_a_foreign_sender_is_denied_before_its_outputs_are_looked_at():
    bridge = Bridge(functions={9: 33})  # a motor: the companion would get FAILED naming 9
    bridge.feed(user2([1500], first=9, sender=GCS))
    [(_, ack)] = bridge.acks()
    assert (ack["result"], ack["result_param2"]) == (mavlink.MAV_RESULT_DENIED, 0)
    assert not any("Channel" in t for t in bridge.texts)


def test_the_parameters_choose_who_is_obeyed():
    bridge = Bridge()
    bridge.param("ARMB_SYSID", 255)
    bridge.param("ARMB_COMPID", 190)  # the ground station is now the one obeyed
    bridge.feed(user2([1100], first=9, sender=GCS), user2([1200], first=9, sender=COMPANION))
    assert bridge.set == [(8, 1100)]
    results = [ack["result"] for _, ack in bridge.acks()]
    assert results == [mavlink.MAV_RESULT_ACCEPTED, mavlink.MAV_RESULT_DENIED]
    assert bridge.texts[-1] == "armbridge: denied 1/191: not ARMB_SYSID/COMPID"


def test_sysid_0_follows_the_vehicles_own_system_id():
    bridge = Bridge(sysid=7)
    bridge.feed(
        user2([1100], first=9, target=(7, 1), sender=(7, 191)),
        user2([1200], first=9, target=(7, 1), sender=(1, 191)),
    )
    assert bridge.set == [(8, 1100)]
    results = [ack["result"] for _, ack in bridge.acks()]
    assert results == [mavlink.MAV_RESULT_ACCEPTED, mavlink.MAV_RESULT_DENIED]


def test_a_flood_of_foreign_commands_is_each_denied_but_said_once_per_5_s():
    bridge = Bridge()
    bridge.env.now_ms = 1000
    for _ in range(5):  # 40 frames, eight a run
        bridge.feed(*[user2([1500], first=9, sender=GCS)] * 8)
    acks = bridge.acks()
    assert len(acks) == 40 and {a["result"] for _, a in acks} == {mavlink.MAV_RESULT_DENIED}
    assert bridge.texts.count(DENIED_TEXT) == 1
    bridge.env.now_ms = 5999
    bridge.feed(user2([1500], first=9, sender=GCS))
    assert bridge.texts.count(DENIED_TEXT) == 1
    bridge.env.now_ms = 6000
    bridge.feed(user2([1500], first=9, sender=GCS))
    assert bridge.texts.count(DENIED_TEXT) == 2
    assert bridge.set == []


def test_the_denial_text_interval_survives_the_millisecond_counter_wrapping():
    bridge = Bridge()
    bridge.env.now_ms = 2**32 - 1000
    bridge.feed(user2([1500], first=9, sender=GCS))
    bridge.env.now_ms = 3999  # 4 999 ms later, past the wrap
    bridge.feed(user2([1500], first=9, sender=GCS))
    assert bridge.texts.count(DENIED_TEXT) == 1
    bridge.env.now_ms = 4000
    bridge.feed(user2([1500], first=9, sender=GCS))
    assert bridge.texts.count(DENIED_TEXT) == 2


def test_without_its_parameter_table_the_script_obeys_its_own_defaults():
    bridge = Bridge(add_table_ok=False)  # the key taken by another script
    assert any("no ARMB_ params (key 143 taken?)" in t for t in bridge.texts)
    assert b"ARMB_SYSID" not in list(bridge.env.params)
    bridge.feed(user2([1100], first=9, sender=COMPANION), user2([1200], first=9, sender=GCS))
    assert bridge.set == [(8, 1100)]
    results = [ack["result"] for _, ack in bridge.acks()]
    assert results == [mavlink.MAV_RESULT_ACCEPTED, mavlink.MAV_RESULT_DENIED]


@pytest.mark.parametrize(
    "binding", ["mavlink.block_command", "param.add_table", "millis", "SRV_Channels"]
)
def test_missing_binding_stops_the_script_naming_it(binding):
    lua = lua_impl.LuaRuntime(encoding=None, unpack_returned_tuples=True)
    env = lua.execute(STAND_INS)
    lua.execute(f"{binding} = nil".encode())
    chunk = lua.eval("function(src) return assert(load(src)) end")(script_text().encode())
    assert chunk() is None  # no update function: ArduPilot stops running it
    name = binding.split(".")[-1].encode()
    assert any(name in t and b"need 4.5+" in t for t in env.texts.values())


@settings(max_examples=40)
@given(
    pwms=st.lists(
        st.one_of(st.floats(width=32), st.integers(0, 3000).map(float)), min_size=6, max_size=6
    ),
    first=st.integers(-2, 34).map(float),
    motor=st.integers(1, 16),
)
def test_never_sets_an_output_out_of_range_or_in_use(pwms, first, motor):
    bridge = Bridge(functions={motor: 33})
    frame = as_mavlink_message_t(command_long((*pwms, first)))
    bridge.feed(frame)
    for chan, pwm in bridge.set:
        assert chan + 1 != motor and 1000 <= pwm <= 2000
    [(_, ack)] = bridge.acks()
    # all-or-nothing: accepted means every non-NaN slot was set, refused means none was
    given = [p for p in pwms if not math.isnan(struct.unpack("<f", struct.pack("<f", p))[0])]
    if ack["result"] == mavlink.MAV_RESULT_ACCEPTED:
        assert len(bridge.set) == len(given)
    else:
        assert bridge.set == []
