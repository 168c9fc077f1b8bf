"""The options of the commands that read a sequence folder are written once (``cli_options.InputOptions``): each
such command lists them in its --help and hands what was given to the reader."""

from __future__ import annotations

import dataclasses

import pytest
import typer
from typer.testing import CliRunner

from taichi_gs import cli_options
from taichi_gs.cli import app
from taichi_gs.cli_options import InputOptions
from taichi_gs.errors import InputError

READING_COMMANDS = ("pose", "import", "reconstruct")
GIVEN = ["--fx", "500", "--fy", "501", "--cx", "319.5", "--cy", "239.5", "--depth-scale", "1000",
         "--trust-depth-scale", "--time-tolerance", "0.01", "--format", "tum", "--camera", "fr1", "--every", "2",
         "--scale", "0.5", "--first", "3", "--count", "4"]
EXPECTED = InputOptions(fx=500.0, fy=501.0, cx=319.5, cy=239.5, depth_scale=1000.0, trust_depth_scale=True,
                        time_tolerance=0.01, format="tum", camera="fr1", every=2, scale=0.5, first=3, count=4)


@pytest.fixture
def loads(monkeypatch) -> list[InputOptions]:
    """What the commands ask the reader for; each stops there with a bad-input error."""
    asked = []

    def load(self, folder):
        asked.append(self)
        raise InputError(folder, "stopped by the test", "none")

    monkeypatch.setattr(InputOptions, "load", load)
    return asked


@pytest.mark.parametrize("command", READING_COMMANDS)
def test_a_reading_command_lists_the_input_options_in_order_with_their_defaults(command):
    params = {p.name: p for p in typer.main.get_command(app).get_command(None, command).params}
    names = [f.name for f in dataclasses.fields(InputOptions)]
    listed = [name for name in params if name in names]
    assert listed == names
    assert [params[name].default for name in names] == [f.default for f in dataclasses.fields(InputOptions)]


@pytest.mark.parametrize("command", READING_COMMANDS)
def test_a_reading_command_hands_the_given_input_options_to_the_reader(command, loads, tmp_path):
    result = CliRunner().invoke(app, [command, str(tmp_path), "--out", str(tmp_path.parent / "o"), *GIVEN])
    assert result.exit_code == 2, result.output
    assert loads == [EXPECTED]


@pytest.mark.parametrize("command", READING_COMMANDS)
def test_without_input_options_the_reader_gets_their_defaults(command, loads, tmp_path):
    CliRunner().invoke(app, [command, str(tmp_path), "--out", str(tmp_path.parent / "o")])
    assert loads == [cli_options.AS_FOUND] == [InputOptions()]


def test_import_counts_averaged_frames(loads, tmp_path):
    CliRunner().invoke(app, ["import", str(tmp_path), "--out", str(tmp_path.parent / "o"), "--average", "3",
                             "--count", "2"])
    assert [options.count for options in loads] == [6]
