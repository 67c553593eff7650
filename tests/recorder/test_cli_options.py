"""The options of manisplat-record, manisplat-replay and manisplat-calibrate (issue 11): every
option and positional says what it does and shows its default, no reST markup reaches --help,
every numeric flag refuses nonsense as a usage error naming the flag, and the packages these
command lines live in load their public names lazily."""

from __future__ import annotations

import argparse
import importlib
import re
from pathlib import Path
from typing import Callable, Iterator

import pytest

from manisplat.calib import cli as calibrate_cli
from manisplat.drivers import replay_cli
from manisplat.recorder import cli as record_cli

PARSERS = {"manisplat-record": record_cli.build_parser, "manisplat-replay": replay_cli.build_parser,
           "manisplat-calibrate": calibrate_cli.build_parser}
MAINS: dict[str, Callable[[list[str]], int]] = {"manisplat-record": record_cli.main,
                                                "manisplat-replay": replay_cli.main,
                                                "manisplat-calibrate": calibrate_cli.main}

# (command line, the arguments before the flag, the flag, values it must refuse)
BAD_VALUES = [
    ("manisplat-record", [], "--fps", ["0", "-30", "nan", "inf", "x"]),
    ("manisplat-record", [], "--size", ["640", "0x400", "640x-1", "axb"]),
    ("manisplat-record", [], "--camera", ["usb", "replay:", "cam=usb", "cam=replay:", "cam=oak:"]),
    ("manisplat-record", [], "--max-skew-ms", ["0", "-5", "nan", "inf"]),
    ("manisplat-record", [], "--latency-ms", ["nan", "inf", "-inf", "1500", "-1001", "x"]),
    ("manisplat-record", [], "--episodes", ["0", "-1", "1.5", "nan"]),
    ("manisplat-record", [], "--duration", ["0", "-1", "nan", "inf"]),
    ("manisplat-record", [], "--max-gap-ms", ["0", "-5", "nan", "inf"]),
    ("manisplat-replay", ["ep"], "--sim-start", ["nan,0,0,0,0,0", "0,0,0,0,0,inf", "1,2", "a,b,c,d,e,f"]),
    ("manisplat-replay", ["ep"], "--speed", ["0", "-1", "nan", "inf"]),
    ("manisplat-replay", ["ep"], "--arm-speed-pct", ["0", "101", "50.5", "nan"]),
    ("manisplat-replay", ["ep"], "--max-tracking-error-deg", ["0", "-1", "nan", "inf"]),
    ("manisplat-replay", ["ep"], "--max-start-distance-deg", ["0", "nan", "inf"]),
    ("manisplat-replay", ["ep"], "--max-step-deg", ["0", "-3", "nan"]),
    ("manisplat-replay", ["ep"], "--feedback-timeout-ms", ["0", "nan", "inf"]),
    ("manisplat-replay", ["ep"], "--arm", ["left", "=can0", "left="]),
    ("manisplat-replay", ["ep"], "--min-arm-clearance-mm", ["-1", "nan", "inf"]),
    ("manisplat-calibrate", ["board"], "--squares-x", ["0", "1", "2.5", "nan"]),
    ("manisplat-calibrate", ["board"], "--squares-y", ["1", "-4"]),
    ("manisplat-calibrate", ["board"], "--square-mm", ["0", "-30", "nan", "inf"]),
    ("manisplat-calibrate", ["board"], "--marker-mm", ["0", "nan", "inf"]),
    ("manisplat-calibrate", ["board"], "--px-per-mm", ["0", "2.5", "inf"]),
    ("manisplat-calibrate", ["intrinsics", "--out", "i.json"], "--width", ["0", "-1280", "nan"]),
    ("manisplat-calibrate", ["intrinsics", "--out", "i.json"], "--height", ["0", "7.5"]),
    ("manisplat-calibrate", ["intrinsics", "--out", "i.json"], "--step", ["0", "-2"]),
    ("manisplat-calibrate", ["intrinsics", "--out", "i.json"], "--min-coverage", ["-0.1", "1.5", "nan", "inf"]),
    ("manisplat-calibrate", ["capture", "--board", "b.json", "--out", "o"], "--settle", ["0", "nan"]),
    ("manisplat-calibrate", ["capture", "--board", "b.json", "--out", "o"], "--frames-per-pose", ["0", "1.5"]),
    ("manisplat-calibrate", ["capture", "--board", "b.json", "--out", "o"], "--max-poses", ["0", "-1"]),
    ("manisplat-calibrate", ["capture", "--board", "b.json", "--out", "o"], "--width", ["0", "inf"]),
    ("manisplat-calibrate", ["capture", "--board", "b.json", "--out", "o"], "--height", ["-720"]),
    ("manisplat-calibrate", ["capture", "--board", "b.json", "--out", "o"], "--fps", ["0", "nan", "inf"]),
    ("manisplat-calibrate", ["solve", "ep", "--board", "b.json", "--out", "c.json"], "--corner-offset",
     ["nan", "inf", "-inf", "x"]),
    ("manisplat-calibrate", ["solve", "ep", "--board", "b.json", "--out", "c.json"], "--max-joint-speed",
     ["0", "nan"]),
    ("manisplat-calibrate", ["solve", "ep", "--board", "b.json", "--out", "c.json"], "--max-offset", ["0", "inf"]),
    ("manisplat-calibrate", ["solve-rig", "ep", "--board", "b.json", "--out", "r.json"], "--corner-offset",
     ["nan", "inf", "x"]),
    ("manisplat-calibrate", ["solve-rig", "ep", "--board", "b.json", "--out", "r.json"], "--max-joint-speed",
     ["0", "nan"]),
    ("manisplat-calibrate", ["latency", "ep"], "--max-offset", ["0", "-0.1", "nan"]),
    ("manisplat-calibrate", ["latency", "ep"], "--max-span", ["0", "nan", "inf"]),
]


def all_parsers(parser: argparse.ArgumentParser) -> Iterator[argparse.ArgumentParser]:
    """``parser`` and every subcommand's parser under it."""
    yield parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                yield from all_parsers(sub)


def options(parser: argparse.ArgumentParser) -> Iterator[argparse.Action]:
    """The options and positionals a user types (not --help, not the subcommand choice)."""
    for action in parser._actions:
        if not isinstance(action, (argparse._HelpAction, argparse._SubParsersAction)):
            yield action


def help_problems(parser: argparse.ArgumentParser) -> list[str]:
    """Options without a help text, or whose help does not show their default."""
    problems = []
    formatter = parser._get_formatter()
    for action in options(parser):
        name = f"{parser.prog} {'/'.join(action.option_strings) or action.dest}"
        text = formatter._expand_help(action) if action.help else ""
        if not text.strip():
            problems.append(f"{name}: no help")
            continue
        default = action.default
        if default is None or default is False or default == argparse.SUPPRESS or action.required:
            continue
        if isinstance(action, argparse._CountAction):  # -v: the default is "not given", said in words
            shown = "default"
        else:
            shown = f"{default:g}" if isinstance(default, (int, float)) else str(default)
        if "default" not in text or shown not in text:
            problems.append(f"{name}: the help does not show the default {shown!r}: {text!r}")
    return problems


@pytest.mark.parametrize("command", PARSERS)
def test_every_option_says_what_it_does_and_its_default(command: str) -> None:
    problems = [p for parser in all_parsers(PARSERS[command]()) for p in help_problems(parser)]
    assert problems == []


@pytest.mark.parametrize("command", PARSERS)
def test_help_shows_no_rest_markup(command: str) -> None:
    for parser in all_parsers(PARSERS[command]()):
        text = parser.format_help()
        assert "``" not in text and not re.search(r":\w+:`", text), f"{parser.prog} --help:\n{text}"


@pytest.mark.parametrize(("command", "before", "flag", "values"), BAD_VALUES,
                         ids=[f"{c} {f}" for c, _, f, _ in BAD_VALUES])
def test_nonsense_numbers_are_usage_errors_naming_the_flag(command: str, before: list[str], flag: str,
                                                           values: list[str], capsys: pytest.CaptureFixture) -> None:
    for value in values:
        with pytest.raises(SystemExit) as exc:
            MAINS[command]([*before, f"{flag}={value}"])
        err = capsys.readouterr().err
        assert exc.value.code == 2, f"{command} {flag}={value} was accepted"
        assert f"argument {flag}" in err and "error" in err, err


@pytest.mark.parametrize("command", PARSERS)
def test_every_option_that_converts_its_value_is_checked_above(command: str) -> None:
    covered = {(command, before[0] if command == "manisplat-calibrate" else None, flag)
               for c, before, flag, _ in BAD_VALUES if c == command}
    top = PARSERS[command]()
    missing = []
    for parser in all_parsers(top):
        sub = parser.prog.split()[-1] if parser is not top else None
        for action in options(parser):
            if action.type not in (None, Path) and action.option_strings:
                if (command, sub, action.option_strings[-1]) not in covered:
                    missing.append(f"{parser.prog} {action.option_strings[-1]}")
    assert missing == []


@pytest.mark.parametrize("package", ["manisplat.recorder", "manisplat.calib", "manisplat.drivers"])
def test_every_public_name_of_the_packages_imports(package: str) -> None:
    module = importlib.import_module(package)
    for name in module.__all__:
        assert getattr(module, name) is not None, name
    assert set(module.__all__) <= set(dir(module))
    namespace: dict[str, object] = {}
    exec(f"from {package} import *", namespace)  # noqa: S102 - what `from package import *` gives a user
    assert set(module.__all__) <= set(namespace)
