"""Every verb of the command line with random arguments and random files: an exit code and a
message, never a traceback. ``demo`` and a ``run`` that could start are left out (they start
processes); everything else runs in-process, against a socket path where no daemon listens."""

from __future__ import annotations

import os

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from companion.daemon.cli import main

VERBS = [
    "run",
    "check-config",
    "doctor",
    "solve",
    "goto",
    "trajectory",
    "status",
    "park",
    "stop",
    "resume",
]
FLAGS = [
    "--config", "--socket", "--timeout-s", "--wait", "--json", "--watch", "--arm", "--tip-link",
    "--budget-ms", "--tol-pos-cm", "--tol-ori-deg", "--seed", "--listen-s", "-v", "-q",
    "--log-level", "--help", "--ceiling-ms", "--method", "--pop-size", "--mutation-f",
    "--crossover-cr", "--lm-iterations", "--stall-generations", "--stall-gain",
]  # fmt: skip
NUMBERS = ["0", "-1", "1e308", "-1e308", "nan", "inf", "-inf", "1e-300", "45", "3.5", "0x10", ""]
TEXTS = ["", "[", "{}", "[[0,1,2,3,4,5,6]]", '{"points": 3}', "[" * 5000, "\0\1\2", "é",
         "[link]\nurl = 5\n", '[link]\nurl = "udp://:0"\n[arm]\nfile = 3\n', "t_s,x\n1,2\n",
         "0,1,2,3,4,5,6\n" * 3,
         "0,1,2,3,4,5,nan\n", "1,1,1,1,1,1,1\n0,1,1,1,1,1,1\n", "a" * 10_000]  # fmt: skip


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    directory = tmp_path_factory.mktemp("fuzz")
    paths = []
    for i, text in enumerate(TEXTS):
        for suffix in (".toml", ".csv", ".json", ".urdf"):
            path = directory / f"f{i}{suffix}"
            path.write_text(text, encoding="utf-8", errors="surrogateescape")
            paths.append(str(path))
    paths += [str(directory / "missing.toml"), str(directory), "/dev/null"]
    return paths


def tokens(paths: list[str]) -> st.SearchStrategy[str]:
    return st.one_of(
        st.sampled_from(FLAGS),
        st.sampled_from(NUMBERS),
        st.sampled_from(paths),
        st.text(max_size=12),
    )


@settings(
    max_examples=250,
    derandomize=True,  # the same argv every run: a failure here is a bug, not luck
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
@given(data=st.data())
def test_every_verb_with_random_arguments_exits_with_a_message(data, files, tmp_path_factory):
    verb = data.draw(st.sampled_from(VERBS))
    pose = []
    if verb in ("solve", "goto") and data.draw(st.booleans()):
        pose = data.draw(st.lists(st.sampled_from(NUMBERS), min_size=6, max_size=6))
    if verb == "trajectory" and data.draw(st.booleans()):
        pose = [data.draw(st.sampled_from(files))]
    argv = [verb, *pose, *data.draw(st.lists(tokens(files), max_size=6))]
    if verb == "run" and "--help" not in argv:
        # Only configs that cannot start: run must refuse them as check-config does.
        argv = ["run", "--config", data.draw(st.sampled_from(files))]
    if verb in ("goto", "trajectory", "status", "park", "stop", "resume"):
        argv += ["--socket", os.path.join(tmp_path_factory.getbasetemp(), "none.sock")]
        argv += ["--timeout-s", "1"]
    if verb == "doctor":
        argv += ["--timeout-s", "0.2", "--listen-s", "0.1"]  # a config that loads: short
    if "--watch" in argv:
        argv.remove("--watch")  # --watch repeats until interrupted
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse: --help and usage errors
        code = exc.code
    assert code in (0, 1, 2, 3), (argv, code)
