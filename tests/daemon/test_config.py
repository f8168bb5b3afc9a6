"""Daemon config: the shipped example loads; every malformed field is named with its range."""

from __future__ import annotations

import dataclasses
import math
from importlib import resources

import pytest

from companion.daemon.config import load_config, parse_config
from companion.errors import ConfigError
from devkit.keepout import QUAD_450

EXAMPLE = (resources.files("companion.daemon") / "examples" / "armbridge.toml").read_text()


def write(tmp_path, text, name="armbridge.toml"):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_example_config_loads_with_documented_defaults(tmp_path):
    cfg = load_config(write(tmp_path, EXAMPLE))
    assert cfg.link.url == "udpout:127.0.0.1:14550"
    assert cfg.link.dialect == "ardupilot" and cfg.link.component_id == 191
    assert cfg.calibration.outputs == (9, 10, 11, 12, 13, 14)
    assert cfg.park_deg == (0, 90, 0, 0, 0, 0)
    assert (cfg.budget_ms, cfg.rate_hz, cfg.joint_speed_deg_s) == (20.0, 20.0, 60.0)
    theta2 = cfg.calibration.joints[1]
    assert (theta2.angle_min_deg, theta2.angle_max_deg) == (0.0, 180.0)


def test_every_value_the_example_sets_is_the_default(tmp_path):
    """The example config says "every field is listed with its default" (park_deg and the
    keep-out volumes excepted, and marked so: a park pose and a vehicle are the user's own, and
    the default is none of either): loaded, it is the same config as the URL alone."""
    example = load_config(write(tmp_path, EXAMPLE))
    minimal = load_config(write(tmp_path, '[link]\nurl = "udpout:127.0.0.1:14550"\n', "min.toml"))
    assert example.park_deg == (0, 90, 0, 0, 0, 0) and minimal.park_deg is None
    assert len(example.keepout) == 9 and minimal.keepout == ()
    same = dataclasses.replace(example, source=minimal.source, park_deg=None, keepout=())
    assert same == minimal


def test_minimal_config_needs_only_the_url(tmp_path):
    cfg = load_config(write(tmp_path, '[link]\nurl = "tcp:127.0.0.1:5760"\n'))
    assert cfg.calibration.outputs == (9, 10, 11, 12, 13, 14)
    assert cfg.link.signing is None
    assert cfg.control_socket == "/run/armbridge/control.sock"  # the shipped unit's directory


def test_ardupilot_lua_dialect_accepted(tmp_path):
    text = '[link]\nurl = "/dev/ttyS1,115200"\ndialect = "ardupilot-lua"\n'
    assert load_config(write(tmp_path, text)).link.dialect == "ardupilot-lua"


def test_signing_key_is_read_relative_to_the_config(tmp_path):
    (tmp_path / "k.key").write_bytes(bytes(range(32)))
    (tmp_path / "k.key").chmod(0o600)
    text = EXAMPLE.replace('# signing_key = "signing.key"', 'signing_key = "k.key"')
    cfg = load_config(write(tmp_path, text))
    assert cfg.link.signing is not None and cfg.link.signing.key == bytes(range(32))


BAD = [
    ("no url", lambda t: t.replace('url = "udpout:127.0.0.1:14550"', ""), "link.url", "missing"),
    (
        "bad url",
        lambda t: t.replace("udpout:127.0.0.1:14550", "carrier-pigeon:1"),
        "link.url",
        "udpin",
    ),
    (
        "dialect",
        lambda t: t.replace('dialect = "ardupilot"', 'dialect = "inav"'),
        "link.dialect",
        "ardupilot, px4",
    ),
    (
        "component",
        lambda t: t.replace("component_id = 191", "component_id = 300"),
        "link.component_id",
        "outside [1, 255]",
    ),
    (
        "negative timeout",
        lambda t: t.replace("loss_timeout_s = 3.0", "loss_timeout_s = -1"),
        "link.loss_timeout_s",
        "-1 outside [2, 60]",
    ),
    (
        "missing key file",
        lambda t: t.replace('# signing_key = "signing.key"', 'signing_key = "nope.key"'),
        "link.signing_key",
        "nope.key",
    ),
    (
        "park outside limits",
        lambda t: t.replace("park_deg = [0, 90, 0, 0, 0, 0]", "park_deg = [0, -10, 0, 0, 0, 0]"),
        "arm.park_deg",
        "outside [0, 180]",
    ),
    (
        "park wrong length",
        lambda t: t.replace("park_deg = [0, 90, 0, 0, 0, 0]", "park_deg = [0, 90]"),
        "arm.park_deg",
        "list of 6",
    ),
    (
        "NaN speed",
        lambda t: t.replace("joint_speed_deg_s = 60.0", "joint_speed_deg_s = nan"),
        "arm.joint_speed_deg_s",
        "finite",
    ),
    (
        "zero budget",
        lambda t: t.replace("budget_ms = 20.0", "budget_ms = 0"),
        "solver.budget_ms",
        "0 outside (0, 1000]",
    ),
    (
        "rate",
        lambda t: t.replace("rate_hz = 20.0", "rate_hz = 5000"),
        "control.rate_hz",
        "5000 outside [1, 400]",
    ),
    ("unknown section", lambda t: t + "\n[extra]\nx = 1\n", "extra", "unknown field"),
    (
        "typo",
        lambda t: t.replace("budget_ms", "budget_msec"),
        "solver.budget_msec",
        "unknown field",
    ),
    (
        "joint count",
        lambda t: t.replace("[[joint]]\noutput = 14\n", ""),
        "joint",
        "5 [[joint]] tables",
    ),
    (
        "output range",
        lambda t: t.replace("output = 14", "output = 17"),
        "joint[6].output",
        "outside [1, 16]",
    ),
    ("duplicate output", lambda t: t.replace("output = 14", "output = 13"), "joint", "unique"),
    (
        "pwm order",
        lambda t: t.replace("output = 9\n", "output = 9\npwm_min_us = 2000\npwm_max_us = 1000\n"),
        "joint[1]",
        "pwm_min_us: 2000 must be below pwm_max_us = 1000",
    ),
    (
        "narrow calibration",
        lambda t: t.replace("output = 10\n", "output = 10\nangle_max_deg = 90\n"),
        "joint[2].angle_max_deg",  # the side that is too narrow
        "must cover",
    ),
    ("not toml", lambda t: t + "\n[[joint\n", "<file>", "not valid TOML"),
    (
        "bad arm file",
        lambda t: t.replace('# file = "my_arm.toml"', 'file = "missing.toml"'),
        "arm.file",
        "cannot read",
    ),
    (
        "mount too far",
        lambda t: t.replace("xyz_cm = [0.0, 0.0, 10.0]", "xyz_cm = [0.0, 0.0, 1e4]"),
        "mount.xyz_cm[2]",
        "outside [-1000, 1000]",
    ),
    (
        "keep-out type",
        lambda t: t.replace('type = "box"', 'type = "cone"'),
        "keepout[1].type",
        "sphere, capsule, box, cylinder",
    ),
    (
        "keep-out field of another type",
        lambda t: t.replace("size_cm = [24.0, 14.0, 10.0]", "radius_cm = 5.0"),
        "keepout[1].radius_cm",
        "unknown field",
    ),
    (
        "keep-out size",
        lambda t: t.replace("size_cm = [24.0, 14.0, 10.0]", "size_cm = [24.0, 0.0, 10.0]"),
        "keepout[1].size_cm[1]",
        "must be > 0",
    ),
    (
        "keep-out radius",
        lambda t: t.replace("radius_cm = 13.0", "radius_cm = -13.0", 1),
        "keepout[2].radius_cm",
        "-13.0 outside (0, 1000]",
    ),
    (
        "keep-out name twice",
        lambda t: t.replace('name = "prop_rear_left"', 'name = "body"'),
        "keepout[3].name",
        "already the name of keepout[1]",
    ),
    (
        "keep-out missing field",
        lambda t: t.replace("length_cm = 2.0\n", "", 1),
        "keepout[2].length_cm",
        "missing",
    ),
    (
        "margin",
        lambda t: t.replace("keepout_margin_cm = 1.0", "keepout_margin_cm = -1"),
        "safety.keepout_margin_cm",
        "outside [0, 50]",
    ),
    (
        "park inside a leg",
        lambda t: t.replace("park_deg = [0, 90, 0, 0, 0, 0]", "park_deg = [45, 90, 0, 0, 0, 0]"),
        "keepout[6]",
        "arm.park_deg [45.0, 90.0, 0.0, 0.0, 0.0, 0.0] is not clear: the link of joint q2 "
        "overlaps keep-out volume 'leg_front_right'",
    ),
]


@pytest.mark.parametrize(("desc", "edit", "field", "words"), BAD, ids=[b[0] for b in BAD])
def test_malformed_field_is_named(tmp_path, desc, edit, field, words):
    path = write(tmp_path, edit(EXAMPLE))
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert info.value.field == field, str(info.value)
    assert words in str(info.value)
    assert str(path) in str(info.value)


# -- bounds with physical meaning (reasons in config.py, the example, docs/configuration.md) --

URL = "udpout:127.0.0.1:14550"

#: (section, key, refused below, lowest accepted, highest accepted, refused above, range text)
BOUNDS = [
    ("control", "rate_hz", 0.999, 1, 400, 400.5, "[1, 400]"),
    ("link", "loss_timeout_s", 1.999, 2, 60, 60.001, "[2, 60]"),
    ("link", "command_timeout_s", 0.0009, 0.001, 20, 60.001, "[0.001, 60]"),
    ("link", "command_retries", -1, 0, 10, 11, "[0, 10]"),
    ("link", "target_component", 0, 1, 255, 256, "[1, 255]"),
    ("solver", "budget_ms", 0, 1e-3, 1000, 1000.001, "(0, 1000]"),
    ("solver", "tol_pos_cm", 9e-7, 1e-6, 10, 10.001, "[1e-06, 10]"),
    ("solver", "tol_ori_deg", 9e-7, 1e-6, 180, 180.001, "[1e-06, 180]"),
    ("arm", "joint_speed_deg_s", 0.999, 1, 1000, 1000.001, "[1, 1000]"),
]


def config(**sections):
    """A config dict: the URL, plus ``section={key: value}`` tables."""
    data: dict = {"link": {"url": URL}}
    for section, table in sections.items():
        if isinstance(table, list):  # [[joint]] rows
            data[section] = table
        else:
            data.setdefault(section, {}).update(table)
    return data


@pytest.mark.parametrize("bound", BOUNDS, ids=[f"{b[0]}.{b[1]}" for b in BOUNDS])
def test_every_bound_accepts_its_ends_and_refuses_past_them_naming_the_range(bound):
    section, key, below, lowest, highest, above, range_text = bound
    for value in (lowest, highest):
        cfg = parse_config(config(**{section: {key: value}}))
        table = cfg.link if section == "link" else cfg
        field = {"arm": key, "solver": key, "control": key}.get(section, key)
        assert getattr(table, field) == value
    for value in (below, above):
        with pytest.raises(ConfigError) as info:
            parse_config(config(**{section: {key: value}}))
        assert info.value.field == f"{section}.{key}", str(info.value)
        assert f"{value!r} outside {range_text}" in str(info.value)


@pytest.mark.parametrize(
    ("section", "values", "field", "words"),
    [
        # What the review found: each of these passed check-config and then broke the daemon.
        ("control", {"rate_hz": 1e-10}, "control.rate_hz", "1e-10 outside [1, 400]"),
        ("link", {"command_timeout_s": 1e300}, "link.command_timeout_s", "outside [0.001, 60]"),
        ("link", {"loss_timeout_s": 1e300}, "link.loss_timeout_s", "outside [2, 60]"),
        ("solver", {"budget_ms": 1e300}, "solver.budget_ms", "outside (0, 1000]"),
        # Each number in range, together an 11-minute wait on one unanswered command.
        (
            "link",
            {"command_timeout_s": 60, "command_retries": 10},
            "link.command_timeout_s",
            "11 x 60 s = 660 s outside (0, 60] s",
        ),
        ("joint", None, "joint[1].trim_us", "501 outside [-500, 500]"),
    ],
    ids=["rate", "command-timeout", "loss-timeout", "budget", "total-ack-wait", "trim"],
)
def test_values_that_broke_the_daemon_are_refused(section, values, field, words):
    if section == "joint":
        data = config(joint=[{"output": 9 + i} for i in range(6)])
        data["joint"][0].update(pwm_min_us=800, pwm_max_us=2200, trim_us=501)
    else:
        data = config(**{section: values})
    with pytest.raises(ConfigError) as info:
        parse_config(data)
    assert info.value.field == field, str(info.value)
    assert words in str(info.value)


def test_an_absurdly_slow_joint_speed_is_refused_naming_the_range():
    # A speed that would leave the arm hanging mid-motion for ever (1e-300 deg/s).
    with pytest.raises(ConfigError) as info:
        parse_config(config(arm={"joint_speed_deg_s": 1e-300}))
    assert info.value.field == "arm.joint_speed_deg_s"
    assert "1e-300 outside [1, 1000]" in str(info.value)


def test_command_wait_of_exactly_a_minute_is_accepted():
    cfg = parse_config(config(link={"command_timeout_s": 20, "command_retries": 2}))
    assert (cfg.link.command_retries + 1) * cfg.link.command_timeout_s == 60


def test_target_component_pins_the_autopilot_component(tmp_path):
    text = EXAMPLE.replace("# target_component = 1 ", "target_component = 1 ")
    assert text != EXAMPLE
    assert load_config(write(tmp_path, text)).link.target_component == 1
    assert load_config(write(tmp_path, EXAMPLE)).link.target_component is None


# -- the calibration covers the arm: limits and park map into each servo's PWM range -----------


def joints(**theta2):
    """Six default [[joint]] rows, the second (theta2: 0…180 deg) with ``theta2`` set."""
    rows = [{"output": 9 + i} for i in range(6)]
    rows[1].update(theta2)
    return rows


def test_the_reviews_trim_with_park_at_170_is_refused_naming_trim_angle_pwm_and_range():
    with pytest.raises(ConfigError) as info:
        parse_config(config(joint=joints(trim_us=100), arm={"park_deg": [0, 170, 0, 0, 0, 0]}))
    assert info.value.field == "joint[2].trim_us"
    message = str(info.value)
    assert "upper limit 180 deg" in message and "2100 µs" in message
    assert "outside [1000, 2000] µs" in message


def test_reversal_is_applied_before_the_check():
    # Reversed, 180 deg maps to 1000 us: a negative trim pushes that end out, not the other.
    with pytest.raises(ConfigError) as info:
        parse_config(config(joint=joints(reversed=True, trim_us=-1)))
    assert info.value.field == "joint[2].trim_us"
    assert "upper limit 180 deg" in str(info.value) and "reversed" in str(info.value)
    assert "999 µs" in str(info.value)
    with pytest.raises(ConfigError, match="lower limit 0 deg"):
        parse_config(config(joint=joints(reversed=True, trim_us=1)))


def test_a_trim_fits_once_the_calibrated_range_leaves_room_for_it():
    # theta2 calibrated over [-18, 198] deg: its limits 0 and 180 map to 1083.3 and 1916.7 us,
    # so a trim of up to +83 us keeps 180 deg at 2000 us or below; +84 is 2001 us.
    wide = {"angle_min_deg": -18, "angle_max_deg": 198}
    cfg = parse_config(config(joint=joints(**wide, trim_us=83)))
    assert cfg.calibration.joints[1].angle_to_pwm_us(180.0) == 2000
    assert parse_config(config(joint=joints(**wide, trim_us=-83))).calibration
    with pytest.raises(ConfigError) as info:
        parse_config(config(joint=joints(**wide, trim_us=84)))
    assert info.value.field == "joint[2].trim_us" and "2001 µs" in str(info.value)
    with pytest.raises(ConfigError, match="lower limit 0 deg .* 999 µs"):
        parse_config(config(joint=joints(**wide, trim_us=-84)))


def test_a_calibrated_limit_equal_to_the_arms_but_for_the_radian_round_trip(tmp_path):
    # The arm stores -127 deg as radians: math.degrees brings back -127.00000000000001, and that
    # is what the solver answers at the limit. A calibration written as -127 must map it.
    assert math.degrees(math.radians(-127)) < -127 < 127 < math.degrees(math.radians(127))
    arm = ['convention = "standard"', 'length_unit = "cm"', "dof = 1"]
    arm += ["[[joint]]", "alpha_deg = 0", "a = 10", "d = 0", "min_deg = -127", "max_deg = 127"]
    (tmp_path / "one.toml").write_text("\n".join(arm) + "\n")
    text = (
        f'[link]\nurl = "{URL}"\n[arm]\nfile = "one.toml"\n'
        "[[joint]]\noutput = 9\nangle_min_deg = -127\nangle_max_deg = 127\n"
    )
    cfg = load_config(write(tmp_path, text))
    joint, cal = cfg.arm.joints[0], cfg.calibration.joints[0]
    assert cal.angle_to_pwm_us(math.degrees(joint.min_rad)) == 1000
    assert cal.angle_to_pwm_us(math.degrees(joint.max_rad)) == 2000


def test_every_default_end_maps_exactly_onto_the_servo_range():
    cfg = parse_config(config())
    for joint, cal in zip(cfg.arm.joints, cfg.calibration.joints, strict=True):
        ends = (math.degrees(joint.min_rad), math.degrees(joint.max_rad))
        assert [cal.angle_to_pwm_us(a) for a in ends] == [1000, 2000]


# -- link.signing_key = "credential:NAME" (systemd's LoadCredential=, the shipped unit) ----------

CREDENTIAL_CONFIG = '[link]\nurl = "tcp:127.0.0.1:5760"\nsigning_key = "credential:signing.key"\n'


def test_a_credential_key_is_read_from_the_credentials_directory(tmp_path, monkeypatch):
    creds = tmp_path / "creds"
    creds.mkdir()
    (creds / "signing.key").write_bytes(bytes(range(32)))
    (creds / "signing.key").chmod(0o600)
    monkeypatch.setenv("CREDENTIALS_DIRECTORY", str(creds))
    cfg = load_config(write(tmp_path, CREDENTIAL_CONFIG))
    assert cfg.link.signing is not None and cfg.link.signing.key == bytes(range(32))


def test_a_credential_key_without_the_credentials_directory_names_the_way_out(
    tmp_path, monkeypatch
):
    monkeypatch.delenv("CREDENTIALS_DIRECTORY", raising=False)
    with pytest.raises(ConfigError) as refused:
        load_config(write(tmp_path, CREDENTIAL_CONFIG))
    assert refused.value.field == "link.signing_key"
    assert "LoadCredential=signing.key:" in str(refused.value)
    assert "CREDENTIALS_DIRECTORY=" in str(refused.value)


@pytest.mark.parametrize("name", ["", "../signing.key", "a/b", ".."])
def test_a_credential_name_must_be_a_file_name(tmp_path, monkeypatch, name):
    monkeypatch.setenv("CREDENTIALS_DIRECTORY", str(tmp_path))
    text = CREDENTIAL_CONFIG.replace("credential:signing.key", f"credential:{name}")
    with pytest.raises(ConfigError, match="must be a file name") as refused:
        load_config(write(tmp_path, text))
    assert refused.value.field == "link.signing_key"


def test_a_missing_credential_is_named_like_a_missing_key_file(tmp_path, monkeypatch):
    monkeypatch.setenv("CREDENTIALS_DIRECTORY", str(tmp_path / "empty"))
    with pytest.raises(ConfigError) as refused:
        load_config(write(tmp_path, CREDENTIAL_CONFIG))
    assert refused.value.field == "link.signing_key"
    assert "signing.key" in str(refused.value)


def test_a_urdf_arm_file_loads_and_a_prismatic_arm_is_refused_naming_the_joint(tmp_path):
    from importlib import resources as res

    arms = res.files("companion.kinematics") / "arms"
    urdf = tmp_path / "ur5.urdf"
    urdf.write_text((arms / "ur5.urdf").read_text())
    cfg = load_config(
        write(tmp_path, '[link]\nurl = "udpout:127.0.0.1:14550"\n[arm]\nfile = "ur5.urdf"\n')
    )
    assert cfg.arm.dof == 6
    stanford = tmp_path / "stanford.toml"
    stanford.write_text((arms / "stanford.toml").read_text())
    with pytest.raises(ConfigError) as info:
        load_config(
            write(
                tmp_path,
                '[link]\nurl = "udpout:127.0.0.1:14550"\n[arm]\nfile = "stanford.toml"\n',
                "s.toml",
            )
        )
    assert info.value.field == "arm.file" and "is prismatic" in str(info.value)


# -- keep-out volumes -----------------------------------------------------------------------------


def test_example_keepout_volumes_and_mount(tmp_path):
    cfg = load_config(write(tmp_path, EXAMPLE))
    names = [v.name for v in cfg.keepout]
    assert names[0] == "body" and len([n for n in names if n.startswith("prop_")]) == 4
    assert cfg.mount.xyz_cm == (0.0, 0.0, 10.0) and cfg.keepout_margin_cm == 1.0
    assert cfg.keepout_check().check(cfg.arm.q_from_user(cfg.park_deg)) is None
    # The quad the tests and bench/keepout.py use is this one, field for field.
    renamed = [dataclasses.replace(v, name=v.name.replace("front_right", "fr")
                                   .replace("rear_left", "rl").replace("front_left", "fl")
                                   .replace("rear_right", "rr")) for v in cfg.keepout]  # fmt: skip
    assert renamed == list(QUAD_450)


def test_empty_keepout_list_and_the_start_pose(tmp_path):
    assert parse_config(config(keepout=[])).keepout == ()
    # Without park_deg the start pose is mid-range, [0, 90, 0, 0, 0, 10]: clear of a sphere
    # ahead of the hand, refused once the sphere sits on the upper arm.
    ball = {"name": "ball", "type": "sphere", "center_cm": [90.0, 0.0, 10.0], "radius_cm": 5.0}
    assert len(parse_config(config(keepout=[ball])).keepout) == 1
    with pytest.raises(ConfigError) as info:
        parse_config(config(keepout=[dict(ball, center_cm=[20.0, 0.0, 10.0])]))
    assert info.value.field == "keepout[1]"
    assert "the start pose [0.0, 90.0, 0.0, 0.0, 0.0, 10.0]" in str(info.value)
    assert "'ball'" in str(info.value) and "q2" in str(info.value)


def test_keepout_needs_an_arm_with_shapes(tmp_path):
    arm = (resources.files("companion.kinematics") / "arms" / "paper_arm.toml").read_text()
    bare = "\n".join(line for line in arm.splitlines() if "link_radius" not in line)
    (tmp_path / "bare.toml").write_text(bare)
    ball = {"name": "ball", "type": "sphere", "center_cm": [90.0, 0.0, 10.0], "radius_cm": 5.0}
    data = config(arm={"file": "bare.toml"}, keepout=[ball])
    with pytest.raises(ConfigError) as info:
        parse_config(data, source=str(tmp_path / "c.toml"))
    assert info.value.field == "keepout" and "no link shapes" in str(info.value)
    assert parse_config(config(arm={"file": "bare.toml"}), source=str(tmp_path / "c.toml"))


def test_arm_tip_link_chooses_where_a_urdf_arm_ends_and_is_refused_without_one(tmp_path):
    from importlib import resources as res

    urdf = tmp_path / "ur5.urdf"
    urdf.write_text((res.files("companion.kinematics") / "arms" / "ur5.urdf").read_text())
    head = '[link]\nurl = "udpout:127.0.0.1:14550"\n[arm]\n'
    whole = load_config(write(tmp_path, head + 'file = "ur5.urdf"\n', "w.toml")).arm
    cfg = load_config(write(tmp_path, head + 'file = "ur5.urdf"\ntip_link = "link6"\n'))
    assert cfg.arm.dof == 6  # the same joints, without the flange's offset
    zero = [0.0] * 6
    assert cfg.arm.fk(zero).as_tuple() != whole.fk(zero).as_tuple()
    with pytest.raises(ConfigError) as info:
        load_config(write(tmp_path, head + 'file = "ur5.urdf"\ntip_link = "nowhere"\n', "a.toml"))
    assert info.value.field == "arm.file" and "nowhere" in str(info.value)
    with pytest.raises(ConfigError) as info:
        load_config(write(tmp_path, head + 'tip_link = "link4"\n', "b.toml"))
    assert info.value.field == "arm.tip_link"


# -- the search: method and settings ---------------------------------------------------------------

#: (key, the SolverSettings field, refused below, lowest accepted, highest accepted, refused
#: above, range text)
SEARCH_BOUNDS = [
    ("pop_size", "pop_size", 3, 4, 100, 101, "[4, 100]"),
    ("mutation_f", "F", 0, 1e-3, 2, 2.001, "(0, 2]"),
    ("crossover_cr", "Cr", -0.001, 0, 1, 1.001, "[0, 1]"),
    ("lm_iterations", "lm_iterations", -1, 0, 100, 101, "[0, 100]"),
    ("stall_generations", "stall_generations", 0, 1, 10_000, 10_001, "[1, 10000]"),
    ("stall_gain", "stall_gain", -0.001, 0, 1, 1.001, "[0, 1]"),
]


@pytest.mark.parametrize("bound", SEARCH_BOUNDS, ids=[b[0] for b in SEARCH_BOUNDS])
def test_every_search_setting_accepts_its_ends_and_refuses_past_them(bound):
    key, field, below, lowest, highest, above, range_text = bound
    # "memetic" uses every one of them ("restarts" no DE setting, "de" no LM).
    for value in (lowest, highest):
        settings = parse_config(config(solver={"method": "memetic", key: value})).search_settings
        assert getattr(settings, field) == value
    for value in (below, above):
        with pytest.raises(ConfigError) as info:
            parse_config(config(solver={"method": "memetic", key: value}))
        assert info.value.field == f"solver.{key}", str(info.value)
        assert f"{value!r} outside {range_text}" in str(info.value)


def test_the_search_defaults_to_the_methods_own_settings():
    from companion.daemon.config import SOLVER_METHOD, SOLVER_METHODS
    from companion.ik import DEFAULT_METHOD, DEFAULT_SETTINGS, METHODS

    assert SOLVER_METHODS == tuple(METHODS) and SOLVER_METHOD == DEFAULT_METHOD
    default = parse_config(config())
    assert default.solver_method == "restarts" and default.search_settings is DEFAULT_SETTINGS
    memetic = parse_config(config(solver={"method": "memetic"}))
    assert memetic.search_settings is METHODS["memetic"]
    assert memetic.search_settings.stall_generations >= 1  # DE generations between restarts
    de = parse_config(config(solver={"method": "de"}))
    assert de.solver_method == "de" and de.search_settings is METHODS["de"]
    s = de.search_settings
    assert (s.pop_size, s.F, s.Cr, s.lm_iterations) == (12, 0.9, 0.95, 0)  # Table 4, test 9
    tuned = parse_config(config(solver={"method": "de", "pop_size": 20, "crossover_cr": 0.5}))
    assert (tuned.search_settings.pop_size, tuned.search_settings.Cr) == (20, 0.5)
    assert tuned.search_settings.F == 0.9 and tuned.search_settings.lm_iterations == 0


@pytest.mark.parametrize(
    ("solver", "field", "words"),
    [
        ({"method": "ga"}, "solver.method", "'ga' is not one of restarts, memetic, de"),
        ({"method": "de", "lm_iterations": 5}, "solver.lm_iterations", '"de" runs no least-'),
        ({"method": "de", "lm_iterations": 0}, "solver.lm_iterations", '"restarts" or "memetic"'),
        ({"mutation_f": 0.9}, "solver.mutation_f", 'with method = "memetic" or "de"'),
        ({"method": "restarts", "stall_generations": 3}, "solver.stall_generations", "anew"),
        ({"pop_size": 8.0}, "solver.pop_size", "must be an integer"),
    ],
)
def test_a_bad_search_setting_is_named(solver, field, words):
    with pytest.raises(ConfigError) as info:
        parse_config(config(solver=solver))
    assert info.value.field == field, str(info.value)
    assert words in str(info.value)
