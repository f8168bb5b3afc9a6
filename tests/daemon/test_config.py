"""Daemon config: the shipped example loads; every malformed field is named with its range."""

from __future__ import annotations

from importlib import resources

import pytest

from companion.daemon.config import load_config
from companion.errors import ConfigError

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


def test_minimal_config_needs_only_the_url(tmp_path):
    cfg = load_config(write(tmp_path, '[link]\nurl = "tcp:127.0.0.1:5760"\n'))
    assert cfg.calibration.outputs == (9, 10, 11, 12, 13, 14)
    assert cfg.link.signing is None and cfg.control_socket is None


def test_signing_key_is_read_relative_to_the_config(tmp_path):
    (tmp_path / "k.key").write_bytes(bytes(range(32)))
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
        "> 0",
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
        "> 0",
    ),
    ("rate", lambda t: t.replace("rate_hz = 20.0", "rate_hz = 5000"), "control.rate_hz", "outside"),
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
        "pwm",
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
]


@pytest.mark.parametrize(("desc", "edit", "field", "words"), BAD, ids=[b[0] for b in BAD])
def test_malformed_field_is_named(tmp_path, desc, edit, field, words):
    path = write(tmp_path, edit(EXAMPLE))
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert info.value.field == field, str(info.value)
    assert words in str(info.value)
    assert str(path) in str(info.value)
