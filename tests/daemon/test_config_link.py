"""``[link]`` settings: ``allowed_senders`` (who may send MAVLink targets),
and a signing state file the daemon must not replace."""

from __future__ import annotations

import pytest

from companion.daemon.cli import main
from companion.daemon.config import parse_config
from companion.errors import ConfigError

URL = "udpout:127.0.0.1:14550"


def link(**fields):
    return parse_config({"link": {"url": URL, **fields}}).link


def test_allowed_senders_default_is_anyone_and_pairs_are_kept():
    assert link().allowed_senders is None
    assert link(allowed_senders=[[255, 190], [1, 191]]).allowed_senders == {(255, 190), (1, 191)}
    assert link(allowed_senders=[]).allowed_senders == frozenset()  # MAVLink may move nothing


@pytest.mark.parametrize(
    ("value", "field", "why"),
    [
        ("255,190", "link.allowed_senders", "must be a list of [system_id, component_id] pairs"),
        ([255, 190], "link.allowed_senders[0]", "must be a [system_id, component_id] pair"),
        ([[255]], "link.allowed_senders[0]", "must be a [system_id, component_id] pair"),
        ([[255, 190], [1, 2, 3]], "link.allowed_senders[1]", "pair"),
        ([[0, 190]], "link.allowed_senders[0]", "system_id=0 must be an integer in [1, 255]"),
        ([[255, 256]], "link.allowed_senders[0]", "component_id=256 must be an integer"),
        ([[255, 1.5]], "link.allowed_senders[0]", "component_id=1.5"),
        ([[True, 1]], "link.allowed_senders[0]", "system_id=True"),
    ],
)
def test_malformed_allowed_senders_are_refused_naming_the_entry(value, field, why):
    with pytest.raises(ConfigError) as info:
        link(allowed_senders=value)
    assert field in str(info.value) and why in str(info.value)


def test_check_config_refuses_a_malformed_allowed_senders(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text(f'[link]\nurl = "{URL}"\nallowed_senders = [[255, 190], [1]]\n')
    assert main(["check-config", str(bad)]) == 2
    assert "link.allowed_senders[1]" in capsys.readouterr().err
