"""Config fuzz: every field of the daemon config, malformed in every way the campaign
knows, makes ``armbridge check-config`` exit 2 with a message naming the file and the field;
``armbridge run`` on a bad config exits 2 and sends nothing to a listening autopilot.

The cases come from ``devkit/campaign.py`` (``config_cases``), which enumerates the fields
from ``companion.daemon.config``'s own key lists: a new field without a fuzz entry fails here.
At the end, a hypothesis property: whatever ``parse_config`` accepts maps the arm's whole range
and park into every servo's PWM range.
"""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
from hypothesis import event, given, settings
from hypothesis import strategies as st

from companion.daemon.config import load_config, parse_config
from companion.errors import ConfigError
from companion.kinematics.arm import Arm
from devkit.campaign import (
    ARM_DOF,
    EXAMPLE_TEXT,
    FIELD_KINDS,
    ConfigCase,
    check_config_case,
    config_cases,
    run_config_fuzz,
    run_rejects_config,
    schema_fields,
)

# A campaign: `armbridge run` subprocesses, every malformed config, a 120-example property.
pytestmark = pytest.mark.slow

SEED = 8


def test_every_config_field_has_fuzz_values_and_is_in_the_example():
    fields = schema_fields()
    assert len(fields) == len(set(fields)) == 44
    assert set(fields) == set(FIELD_KINDS)
    # docs/configuration.md promises the example lists every field with its default.
    for dotted in fields:
        key = dotted.split(".")[1]
        assert re.search(rf"^#?\s*{key}\s*=", EXAMPLE_TEXT, re.M), f"{dotted} not in the example"


def test_every_malformed_config_exits_2_naming_the_field(tmp_path):
    report = run_config_fuzz(tmp_path, seed=SEED)
    assert report.failures == []
    assert set(report.cases) == {
        "wrong_type",
        "out_of_range",
        "missing_required",
        "unknown_key",
        "broken_toml",
        "unreadable",
    }
    assert sum(report.cases.values()) > 700
    # Every field was named by at least one case, every joint row's fields too.
    expected = set()
    for dotted in schema_fields():
        section, key = dotted.split(".")
        if section == "joint":
            expected |= {f"joint[{i}].{key}" for i in range(1, ARM_DOF + 1)}
        else:
            expected.add(dotted)
    assert expected <= report.fields_covered


def test_config_cases_are_seeded(tmp_path):
    runs = []
    for name in ("a", "b"):
        (tmp_path / name).mkdir()
        cases = config_cases(tmp_path / name, np.random.default_rng(SEED))
        runs.append(
            [(c.description, c.path.read_bytes() if c.path.is_file() else None) for c in cases]
        )
    assert runs[0] == runs[1]


# -- what the campaign found: each of these failed before its fix ---------------------------


@pytest.mark.parametrize(
    ("content", "field", "words"),
    [
        # UnicodeDecodeError escaped load_toml: exit 2, but naming neither file nor field.
        (EXAMPLE_TEXT.encode() + b"# caf\xe9\n", "<file>", "not UTF-8"),
        (EXAMPLE_TEXT.encode("utf-16"), "<file>", "not UTF-8"),
        # RecursionError from tomllib: a traceback and exit 1.
        (("x = " + "[" * 5000 + "]" * 5000 + "\n").encode(), "<file>", "nested too deeply"),
        # The calibration too narrow at the top named angle_min_deg.
        (
            EXAMPLE_TEXT.replace("output = 10\n", "output = 10\nangle_max_deg = 5\n").encode(),
            "joint[2].angle_max_deg",
            "must cover",
        ),
        # A socket path longer than sun_path passed check-config and failed at bind in run.
        (
            EXAMPLE_TEXT.replace(
                'socket = "/run/armbridge/control.sock"', f'socket = "/run/{"s" * 110}.sock"'
            ).encode(),
            "control.socket",
            "at most 107",
        ),
    ],
    ids=["latin-1", "utf-16", "deep-nesting", "narrow-max", "socket-too-long"],
)
def test_found_by_the_fuzz_now_names_the_field(tmp_path, content, field, words):
    path = tmp_path / "armbridge.toml"
    path.write_bytes(content)
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert info.value.field == field, str(info.value)
    assert words in str(info.value) and str(path) in str(info.value)


@pytest.mark.parametrize(
    ("edit", "field"),
    [
        (lambda t: t.replace("component_id = 191", "component_id = 0"), "link.component_id"),
        # The control socket is opened first: its directory missing is exit 2 naming it, before
        # the link sends a single HEARTBEAT (it was a traceback, exit 1, after the link was up).
        (
            lambda t: t.replace(
                'socket = "/run/armbridge/control.sock"',
                'socket = "/nonexistent-armbridge-dir/below/control.sock"',
            ),
            "control.socket",
        ),
        # The signing state's directory is only known to be missing when run starts (systemd
        # makes StateDirectory= then): it was a traceback and exit 1.
        (
            lambda t: t.replace(
                '# signing_key = "signing.key"', 'signing_key = "good.key"'
            ).replace(
                '# signing_state = "/var/lib/armbridge/signing.state"',
                'signing_state = "no-such-dir/signing.state"',
            ),
            "link.signing_state",
        ),
    ],
    ids=["component-id", "socket-dir-missing", "signing-state-dir-missing"],
)
def test_run_on_a_bad_config_exits_2_and_sends_nothing(tmp_path, edit, field):
    (tmp_path / "good.key").write_bytes(bytes(range(32)))
    (tmp_path / "good.key").chmod(0o600)
    code, stderr, datagrams = run_rejects_config(tmp_path, edit(EXAMPLE_TEXT))
    assert code == 2, stderr
    assert f": {field}: " in stderr
    assert datagrams == 0


def test_a_case_that_passes_check_config_is_reported(tmp_path):
    # The checker itself must be able to fail: a valid config is not "exit 2 naming a field".
    path = tmp_path / "ok.toml"
    path.write_text(EXAMPLE_TEXT)
    problem = check_config_case(ConfigCase("control", "valid example", path, "link.url"))
    assert problem is not None and "exit 0" in problem


# -- property: whatever parse_config accepts, the arm's whole range maps into the servo's ------

ARM = Arm.default()
LIMITS_DEG = [(math.degrees(j.min_rad), math.degrees(j.max_rad)) for j in ARM.joints]


@st.composite
def calibrations(draw):
    """``(data, park_deg)``: a config of six [[joint]] rows with valid PWM ranges and trims
    within half their span, calibrated angle ranges from exactly the arm's limits to 60 deg
    wider on either side, and maybe a park pose; only the coverage rule can refuse it."""
    rows = []
    for i, (lo, hi) in enumerate(LIMITS_DEG):
        pwm_min = draw(st.integers(500, 2400))
        pwm_max = draw(st.integers(pwm_min + 1, 2500))
        half = min(500, (pwm_max - pwm_min) // 2)
        margin = st.one_of(st.just(0.0), st.floats(1e-6, 60.0))  # past the 1e-9 snap
        rows.append(
            {
                "output": 9 + i,
                "pwm_min_us": pwm_min,
                "pwm_max_us": pwm_max,
                "angle_min_deg": lo - draw(margin),
                "angle_max_deg": hi + draw(margin),
                "reversed": draw(st.booleans()),
                "trim_us": draw(
                    st.one_of(st.just(0), st.integers(-min(half, 20), min(half, 20)))
                    | st.integers(-half, half)
                ),
            }
        )
    park = None
    if draw(st.booleans()):
        park = [lo + draw(st.floats(0.0, 1.0)) * (hi - lo) for lo, hi in LIMITS_DEG]
    data = {"link": {"url": "udpout:127.0.0.1:14550"}, "joint": rows}
    if park is not None:
        data["arm"] = {"park_deg": park}
    return data, park


def spec_pwm_us(row: dict, angle_deg: float) -> int:
    """The calibration's rule, written out from its docstring: linear from
    [angle_min_deg, angle_max_deg] onto [pwm_min_us, pwm_max_us] (swapped when reversed), plus
    trim, rounded to the nearest µs with halves up."""
    fraction = (angle_deg - row["angle_min_deg"]) / (row["angle_max_deg"] - row["angle_min_deg"])
    if row["reversed"]:
        fraction = 1.0 - fraction
    span_us = row["pwm_max_us"] - row["pwm_min_us"]
    return math.floor(row["pwm_min_us"] + fraction * span_us + row["trim_us"] + 0.5)


@settings(max_examples=120)
@given(calibrations(), st.lists(st.floats(0.0, 1.0), min_size=3, max_size=3))
def test_an_accepted_config_maps_the_whole_arm_range_and_park_into_each_servo_range(
    drawn, fractions
):
    data, park = drawn
    ends_inside = all(
        row["pwm_min_us"] <= spec_pwm_us(row, angle) <= row["pwm_max_us"]
        for row, (lo, hi), i in zip(data["joint"], LIMITS_DEG, range(6), strict=True)
        for angle in (lo, hi, *(() if park is None else (park[i],)))
    )
    try:
        cfg = parse_config(data)
    except ConfigError as exc:
        event("refused")
        # Refused only for an end (or the park angle) whose trimmed PWM leaves the range.
        assert not ends_inside, str(exc)
        assert re.fullmatch(r"joint\[[1-6]\]\.trim_us", exc.field), str(exc)
        return
    event("accepted")
    assert ends_inside
    for i, (joint, (lo, hi)) in enumerate(zip(cfg.calibration.joints, LIMITS_DEG, strict=True)):
        angles = [lo, hi, *(lo + f * (hi - lo) for f in fractions)]
        if cfg.park_deg is not None:
            angles.append(cfg.park_deg[i])
        for angle in angles:
            pwm_us = joint.angle_to_pwm_us(angle)  # raises if the daemon would refuse it
            assert joint.pwm_min_us <= pwm_us <= joint.pwm_max_us
            assert pwm_us == spec_pwm_us(data["joint"][i], angle)
