"""Config fuzz (issue 8): every field of the daemon config, malformed in every way the campaign
knows, makes ``armbridge check-config`` exit 2 with a message naming the file and the field;
``armbridge run`` on a bad config exits 2 and sends nothing to a listening autopilot.

The cases come from ``tests/support/campaign.py`` (``config_cases``), which enumerates the fields
from ``companion.daemon.config``'s own key lists: a new field without a fuzz entry fails here.
"""

from __future__ import annotations

import re

import numpy as np
import pytest

from companion.daemon.config import load_config
from companion.errors import ConfigError
from tests.support.campaign import (
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

SEED = 8


def test_every_config_field_has_fuzz_values_and_is_in_the_example():
    fields = schema_fields()
    assert len(fields) == len(set(fields)) == 30
    assert set(fields) == set(FIELD_KINDS)
    # The README promises the example lists every field with its default.
    for dotted in fields:
        key = dotted.split(".")[1]
        assert re.search(rf"^#?\s*{key}\s*=", EXAMPLE_TEXT, re.M), f"{dotted} not in the example"


@pytest.mark.slow
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


@pytest.mark.slow
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
                '# socket = "/run/armbridge/control.sock"', f'socket = "/run/{"s" * 110}.sock"'
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


@pytest.mark.slow
@pytest.mark.parametrize(
    ("edit", "field"),
    [
        (lambda t: t.replace("component_id = 191", "component_id = 0"), "link.component_id"),
        # The control socket is opened first: its directory missing is exit 2 naming it, before
        # the link sends a single HEARTBEAT (it was a traceback, exit 1, after the link was up).
        (
            lambda t: t.replace(
                '# socket = "/run/armbridge/control.sock"',
                'socket = "/nonexistent-armbridge-dir/control.sock"',
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
