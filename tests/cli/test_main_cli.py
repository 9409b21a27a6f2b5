"""The top-level ``keygen`` parser: every sub-command is wired in and its help renders."""

from __future__ import annotations

import pytest

from keygen.cli.main import build_parser

COMMANDS = [
    ["objects", "generate"],
    ["sim", "render"],
    ["expert"],
    ["demos"],
    ["data", "info"],
    ["keypoints", "train"],
    ["keypoints", "eval"],
    ["keypoints", "show"],
    ["train"],
    ["eval"],
    ["benchmark"],
    ["demo"],
]


@pytest.mark.parametrize("command", COMMANDS, ids=" ".join)
def test_every_subcommand_renders_its_help(command, capsys):
    # argparse formats help strings with %-interpolation: a stray '%' only fails when help is shown.
    with pytest.raises(SystemExit) as exc:
        build_parser().parse_args([*command, "--help"])
    assert exc.value.code == 0
    assert "usage: keygen" in capsys.readouterr().out


def test_unknown_command_is_an_error(capsys):
    with pytest.raises(SystemExit) as exc:
        build_parser().parse_args(["no-such-command"])
    assert exc.value.code == 2
