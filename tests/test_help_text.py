"""`trundle COMMAND --help` reads as plain text: no reST markup from the docstrings, every argument
explained, choices listed rather than a module named."""

from __future__ import annotations

import argparse

import pytest

from tests.test_slam_command import simulated_log  # noqa: F401  (a fixture)
from trundle.tools.cli.main import COMMANDS, build_parser, main, plain

NESTED = [["emulate", "lrf"], ["emulate", "can"], ["emulate", "camera"], ["import", "carmen"],
          ["import", "breezyslam"], ["import", "mrclam"]]


@pytest.mark.parametrize("argv", [[c] for c in COMMANDS] + NESTED, ids=" ".join)
def test_help_has_no_markup(argv: list[str], capsys) -> None:
    assert main([*argv, "--help"]) == 0
    out = capsys.readouterr().out
    assert "`" not in out and ":mod:" not in out and ":func:" not in out


def test_plain_strips_roles_and_literals() -> None:
    assert (plain("``--lrf`` URLs (:mod:`trundle.tools.jobs.x`, :func:`~a.b`, `t`)")
            == "--lrf URLs (trundle.tools.jobs.x, a.b, t)")


def _commands(parser: argparse.ArgumentParser, name: str):
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for child, sub in action.choices.items():
                yield from _commands(sub, f"{name} {child}".strip())
    yield name, parser


@pytest.mark.parametrize("command", COMMANDS)
def test_every_argument_is_explained(command: str) -> None:
    for name, parser in _commands(build_parser([command]), ""):
        bare = [a.dest for a in parser._actions if not a.help and not isinstance(a, argparse._SubParsersAction)]
        assert bare == [], f"trundle {name}: {bare} have no help"


def test_export_and_perceive_help_name_their_choices(capsys) -> None:
    main(["export", "--help"])
    out = " ".join(capsys.readouterr().out.split())
    assert "--topic TOPIC the topic to export, e.g. /odom" in out
    assert "--format {csv,ndjson} csv: one row per message" in out
    main(["perceive", "--help"])
    out = " ".join(capsys.readouterr().out.split())
    assert ("--method NAME keypoint detector: sift, surf, orb, akaze, brisk, mser, fast, agast, harris, "
            "shi-tomasi, log, dog, canny, sobel, roberts (default orb)") in out
    assert "trundle.perception" not in out


def test_a_negative_value_is_a_value_not_an_option(simulated_log, tmp_path, capsys) -> None:  # noqa: F811
    """`--heading-glitch -5:30` reaches the option's own check instead of "expected one argument"."""
    log, _ = simulated_log
    assert main(["inject-faults", str(log), "-o", str(tmp_path / "o.mcap"), "--heading-glitch", "-5:30"]) == 2
    assert capsys.readouterr().err == ("trundle inject-faults: heading_glitch at -5 s is outside the log's odometry "
                                       "(0 to 55.50 s after its first reading): nothing would be injected\n")
