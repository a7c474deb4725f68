"""A misspelled option: the usage of the subcommand it was given to, and the nearest option."""

from __future__ import annotations

import pytest

from mapcontainer.cli import build_parser
from services.cli import add_live_commands


def build_mapc_parser():
    parser = build_parser()
    add_live_commands(parser)  # as services.cli.main does
    return parser


@pytest.mark.parametrize(
    ("argv", "usage", "says"),
    [
        (["fleet", "up", "--duraton", "20"], "usage: mapc fleet up", "--duraton 20 (did you mean --duration?)"),
        (["health", "--flet", "x"], "usage: mapc health", "--flet x (did you mean --fleet?)"),
        (
            ["map", "show", "--scenario", "paper-urban", "--aroud", "1,2"],
            "usage: mapc map show",
            "did you mean --around?",
        ),
        (["sim", "paper-urban", "--out", "x", "--sed", "3"], "usage: mapc sim", "--sed 3 (did you mean --seed?)"),
        (["sim", "paper-urban", "--out", "x", "stray"], "usage: mapc sim", "unrecognized arguments: stray"),
    ],
)
def test_a_misspelled_option_gets_the_subcommands_usage_and_a_suggestion(capsys, argv, usage, says) -> None:
    with pytest.raises(SystemExit) as exc:
        build_mapc_parser().parse_args(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith(usage), err
    assert says in err.splitlines()[-1], err
