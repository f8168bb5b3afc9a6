--[[
armbridge_servo.lua: sets up to six servo outputs from one MAVLink COMMAND_LONG, for armbridge's
`ardupilot-lua` servo dialect (one 44-byte frame per arm update instead of one DO_SET_SERVO per
joint, which matters on 57 600 / 115 200 baud telemetry links).

Install: copy this file to the flight controller's SD card in APM/scripts/, set SCR_ENABLE = 1,
reboot. On start it says "armbridge_servo v2 ready" (or why it cannot run) on the ground station.
If armbridge's link.system_id / link.component_id are not its defaults, set ARMB_SYSID /
ARMB_COMPID (below) to them.

The command: COMMAND_LONG, command = MAV_CMD_USER_2 (31011), addressed to this autopilot
(target_system = MAV_SYSID / SYSID_THISMAV, target_component 0 or 1).
  param1..param6  PWM in microseconds for outputs first .. first+5; NaN leaves that output alone
  param7          first output, 1-based (SERVOn numbering)
Answer: one COMMAND_ACK (command 31011) to the sender on the link the command came from:
  MAV_RESULT_ACCEPTED (0): every output given was set;
  MAV_RESULT_DENIED   (2): the sender is not the companion (below): nothing was set, nothing
                           was checked; a STATUSTEXT "denied SYS/COMP: not ARMB_SYSID/COMPID"
                           names the sender, at most once every 5 s however many come;
  MAV_RESULT_FAILED   (4): nothing was set (all-or-nothing: every output is checked before any
                           is set); result_param2 = the first output refused (0: the command's
                           own parameters), and a STATUSTEXT says why.

Who may send it: only the companion, by the sender ids in the frame's header (checked after
the target: a command for another vehicle or component is passed over, not answered). The
script adds two parameters of its own (a table with the prefix ARMB_, key PARAM_TABLE_KEY
below); they show in the ground station's parameter list after its first start, keep their
values through reboots, and a change applies to the next command:
  ARMB_SYSID   the companion's system id; 0 (the default): the autopilot's own, MAV_SYSID, as
               armbridge uses unless its link.system_id says otherwise;
  ARMB_COMPID  the companion's component id; default 191 (MAV_COMP_ID_ONBOARD_COMPUTER),
               armbridge's link.component_id default.
Their defaults are COMPANION_SYSID / COMPANION_COMPID below; if the table cannot be added (its
key taken by another script: change PARAM_TABLE_KEY) the script says so and uses those.
The ids are what the frame says: a device on the same network can write any ids into a frame.
The check keeps a ground station, a second companion or a stray script's USER_2 off the arm; to
keep out someone who forges ids, sign the link (MAVLink 2 signing).

An output is refused unless SERVOn_FUNCTION = 0 (Disabled: nothing else drives it; every other
value, including RC pass-through, motors and GPIO (-1), belongs to something else) and
SERVOn_MIN <= PWM <= SERVOn_MAX with an integer PWM. armbridge's calibration gate is the first
check; this one also catches an autopilot whose outputs were re-mapped behind its back.

What it reads and why it checks: mavlink:receive_chan() returns the C mavlink_message_t as a
string (291 bytes with MAVLink 2's 255-byte payload area: checksum, magic, len, flags, seq,
sysid, compid, 24-bit msgid, then the payload from byte 13). Newer ArduPilot versions change that
layout (a 32-bit sysid variant), so a string of any other length, a magic byte other than 0xFD /
0xFE, another message id or a payload length over COMMAND_LONG's 33 bytes is not parsed: it is
passed over, and a wrong layout is reported once as a STATUSTEXT (nothing is then ever answered,
which armbridge's `doctor` reports as "the script does not answer"). MAVLink 2 drops trailing
zero bytes of a payload; they are restored from `len`, never read from beyond it.

Versions: the bindings used (mavlink:init / register_rx_msgid / receive_chan / send_chan /
block_command with ':' calls, param:get / add_table / add_param, millis,
SRV_Channels:set_output_pwm_chan) are in ArduPilot 4.5 and later; the send-to-ACK figures
armbridge quotes (median 8.9 ms, max 11.5 ms) were measured on ArduCopter 4.7.0-dev SITL. The script checks the bindings it needs at start and stops with a
STATUSTEXT if one is missing.
]]

local SCRIPT_NAME = "armbridge_servo"
local SCRIPT_VERSION = 2

-- The companion, the only sender obeyed: the defaults of ARMB_SYSID / ARMB_COMPID, and what is
-- used if the parameters cannot be added. 0: the autopilot's own system id (MAV_SYSID).
local COMPANION_SYSID = 0
local COMPANION_COMPID = 191 -- MAV_COMP_ID_ONBOARD_COMPUTER, armbridge's link.component_id
-- The script's parameter table: a key no other script on this flight controller uses (0-200).
local PARAM_TABLE_KEY = 143
local PARAM_TABLE_PREFIX = "ARMB_"
-- A refused sender is said on the ground station at most this often (a flood of commands is
-- each answered DENIED, but not each said).
local DENIED_TEXT_MS = 5000

local MAV_CMD_USER_2 = 31011
local COMMAND_LONG_ID = 76
local COMMAND_ACK_ID = 77
local MAV_RESULT_ACCEPTED = 0
local MAV_RESULT_DENIED = 2
local MAV_RESULT_FAILED = 4
local MAV_SEVERITY_WARNING = 4
local MAV_SEVERITY_INFO = 6

-- sizeof(mavlink_message_t) (MAVLink 2 C library, packed): 12 header bytes, 33 * 8 payload,
-- 2 checksum, 13 signature.
local MSG_T_BYTES = 291
local PAYLOAD_AT = 13 -- 1-based index of the payload's first byte in that string
local COMMAND_LONG_LEN = 33
local SLOTS = 6 -- params 1..6
local MAX_OUTPUT = 32 -- SERVO1 .. SERVO32
local LOOP_MS = 5 -- the script's own period (the scripting thread runs below the main loop)
local FRAMES_PER_RUN = 8 -- bound the work of one run; the rest waits for the next

-- A status line is at most 50 characters on the wire.
local function say(severity, text)
  gcs:send_text(severity, string.sub("armbridge: " .. text, 1, 50))
end

local function bindings_missing()
  -- (name, binding) pairs: a table keyed by name would drop a nil binding from its own pairs()
  local globals = { { "mavlink", mavlink }, { "param", param }, { "SRV_Channels", SRV_Channels }, { "millis", millis } }
  for _, entry in ipairs(globals) do
    if entry[2] == nil then
      return entry[1]
    end
  end
  local needed = {
    { "mavlink", mavlink, { "init", "register_rx_msgid", "receive_chan", "send_chan", "block_command" } },
    { "param", param, { "get", "add_table", "add_param" } },
  }
  for _, entry in ipairs(needed) do
    local object_name, object, names = entry[1], entry[2], entry[3]
    for _, name in ipairs(names) do
      local ok, binding = pcall(function()
        return object[name]
      end)
      if not ok or binding == nil then
        return object_name .. ":" .. name
      end
    end
  end
  return nil
end

local function our_sysid()
  -- Renamed from SYSID_THISMAV to MAV_SYSID in 4.7.
  return param:get("MAV_SYSID") or param:get("SYSID_THISMAV")
end

-- ARMB_SYSID / ARMB_COMPID (true), or false with the script's own ids used instead.
local function add_params()
  if not param:add_table(PARAM_TABLE_KEY, PARAM_TABLE_PREFIX, 2) then
    return false
  end
  return param:add_param(PARAM_TABLE_KEY, 1, "SYSID", COMPANION_SYSID)
    and param:add_param(PARAM_TABLE_KEY, 2, "COMPID", COMPANION_COMPID)
end

-- The (system id, component id) the command must come from; read on every command, so a
-- parameter set applies at once.
local function companion_ids()
  local sysid = param:get(PARAM_TABLE_PREFIX .. "SYSID") or COMPANION_SYSID
  local compid = param:get(PARAM_TABLE_PREFIX .. "COMPID") or COMPANION_COMPID
  if sysid == 0 then
    sysid = our_sysid()
  end
  return sysid, compid
end

local layout_reported = false

-- The COMMAND_LONG in `msg` (a mavlink_message_t string) as a table, or nil when it is not one
-- we can read.
local function parse_command_long(msg)
  if type(msg) ~= "string" or #msg ~= MSG_T_BYTES then
    if not layout_reported then
      layout_reported = true
      say(MAV_SEVERITY_WARNING, string.format("frame %d B, need %d: unsupported", type(msg) == "string" and #msg or -1, MSG_T_BYTES))
    end
    return nil
  end
  local magic, len = string.unpack("<BB", msg, 3)
  if magic ~= 0xFD and magic ~= 0xFE then
    return nil
  end
  local sysid, compid, msgid = string.unpack("<BBI3", msg, 8)
  if msgid ~= COMMAND_LONG_ID or len > COMMAND_LONG_LEN then
    return nil
  end
  local payload = string.sub(msg, PAYLOAD_AT, PAYLOAD_AT + len - 1) .. string.rep("\0", COMMAND_LONG_LEN - len)
  local p1, p2, p3, p4, p5, p6, p7, command, target_system, target_component =
    string.unpack("<fffffffI2BB", payload)
  return {
    params = { p1, p2, p3, p4, p5, p6, p7 },
    command = command,
    target_system = target_system,
    target_component = target_component,
    sysid = sysid,
    compid = compid,
  }
end

local function is_integer(x)
  return x == x and x ~= math.huge and x ~= -math.huge and math.floor(x) == x
end

-- Every output of the command checked; returns the list of {channel, pwm} to set, or nil, the
-- refused output (0: the command itself) and the reason.
local function check_outputs(cmd)
  local first = cmd.params[7]
  if not is_integer(first) or first < 1 or first > MAX_OUTPUT then
    return nil, 0, string.format("param7 first output %s not 1-%d", tostring(first), MAX_OUTPUT)
  end
  first = math.tointeger(first) -- the bindings take integers
  local settings = {}
  for slot = 1, SLOTS do
    local pwm = cmd.params[slot]
    if pwm == pwm then -- NaN: leave that output alone
      local output = first + slot - 1
      if output > MAX_OUTPUT then
        return nil, 0, string.format("output %d over %d", output, MAX_OUTPUT)
      end
      local func = param:get(string.format("SERVO%d_FUNCTION", output))
      if func == nil then
        return nil, output, string.format("SERVO%d_FUNCTION missing", output)
      end
      if func ~= 0 then
        -- Same words as ArduPilot's own DO_SET_SERVO refusal, so a reader of the link can
        -- tell which output it was.
        return nil, output, string.format("Channel %d is already in use", output)
      end
      local low = param:get(string.format("SERVO%d_MIN", output))
      local high = param:get(string.format("SERVO%d_MAX", output))
      if low == nil or high == nil then
        return nil, output, string.format("SERVO%d_MIN/MAX missing", output)
      end
      if not is_integer(pwm) or pwm < low or pwm > high then
        return nil, output, string.format("out%d pwm %s not in %d-%d", output, tostring(pwm), math.floor(low), math.floor(high))
      end
      settings[#settings + 1] = { output - 1, math.tointeger(pwm) }
    end
  end
  if #settings == 0 then
    return nil, 0, "no PWM in params 1-6"
  end
  return settings
end

local function send_ack(chan, cmd, result, result_param2)
  local payload = string.pack(
    "<I2BBi4BB",
    MAV_CMD_USER_2,
    result,
    0, -- progress
    result_param2,
    cmd.sysid,
    cmd.compid
  )
  return mavlink:send_chan(chan, COMMAND_ACK_ID, payload)
end

local denied_said_ms = nil -- when a refused sender was last said (nil: never)

-- A sender other than the companion: DENIED, nothing checked or set; said at most every
-- DENIED_TEXT_MS (millis() wraps after 49 days: the difference is taken modulo 2^32).
local function deny(chan, cmd)
  local now = millis():toint()
  if denied_said_ms == nil or ((now - denied_said_ms) & 0xFFFFFFFF) >= DENIED_TEXT_MS then
    denied_said_ms = now
    say(MAV_SEVERITY_WARNING, string.format("denied %d/%d: not ARMB_SYSID/COMPID", cmd.sysid, cmd.compid))
  end
  send_ack(chan, cmd, MAV_RESULT_DENIED, 0)
end

-- One received frame; returns true if it was our command (answered).
local function handle(msg, chan)
  local cmd = parse_command_long(msg)
  if cmd == nil or cmd.command ~= MAV_CMD_USER_2 then
    return false
  end
  if cmd.target_system ~= our_sysid() or (cmd.target_component ~= 0 and cmd.target_component ~= 1) then
    return false -- for another vehicle or component: ArduPilot's routing forwards it
  end
  local sysid, compid = companion_ids()
  if cmd.sysid ~= sysid or cmd.compid ~= compid then
    deny(chan, cmd)
    return true
  end
  local settings, refused, reason = check_outputs(cmd)
  if settings == nil then
    say(MAV_SEVERITY_WARNING, reason .. "; none set")
    send_ack(chan, cmd, MAV_RESULT_FAILED, refused)
    return true
  end
  for _, setting in ipairs(settings) do
    SRV_Channels:set_output_pwm_chan(setting[1], setting[2])
  end
  send_ack(chan, cmd, MAV_RESULT_ACCEPTED, 0)
  return true
end

local function update()
  for _ = 1, FRAMES_PER_RUN do
    local msg, chan = mavlink:receive_chan()
    if msg == nil then
      break
    end
    local ok, err = pcall(handle, msg, chan)
    if not ok then
      say(MAV_SEVERITY_WARNING, tostring(err))
    end
  end
  return update, LOOP_MS
end

local missing = bindings_missing()
if missing ~= nil then
  say(MAV_SEVERITY_WARNING, "no " .. missing .. ", need 4.5+")
  return
end
-- Queue depth and number of message ids: both 8, so either argument order (it changed between
-- versions of the binding's documentation) gives a deep enough queue.
mavlink:init(8, 8)
mavlink:register_rx_msgid(COMMAND_LONG_ID)
-- Without this ArduPilot answers MAV_CMD_USER_2 itself with UNSUPPORTED.
mavlink:block_command(MAV_CMD_USER_2)
if not add_params() then
  say(MAV_SEVERITY_WARNING, string.format("no ARMB_ params (key %d taken?)", PARAM_TABLE_KEY))
end
say(MAV_SEVERITY_INFO, string.format("%s v%d ready", SCRIPT_NAME, SCRIPT_VERSION))

return update, LOOP_MS
