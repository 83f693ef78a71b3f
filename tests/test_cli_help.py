"""``eventocc-receiver``'s help and progress: every command described in plain text, with
``-q``, every option explained with its default; a progress bar that never runs past its end."""

from __future__ import annotations

import functools
import io
import warnings

import numpy as np
import pytest
from tqdm import tqdm

from eventocc.receiver.cli import COMMANDS, build_parser, main
from eventocc.receiver.commands import read_with_progress


def command_help(name: str, capsys) -> str:
    with pytest.raises(SystemExit) as stopped:
        main([name, "--help"])
    assert stopped.value.code == 0
    return capsys.readouterr().out


@pytest.mark.parametrize("name", COMMANDS)
def test_every_command_says_what_it_does_in_plain_text_and_takes_q(name: str, capsys) -> None:
    text = command_help(name, capsys)
    description = text.split("\n\n")[1]
    assert description.startswith(f"eventocc-receiver {name}"), text
    assert "``" not in text and "`" not in description
    assert "-q, --quiet" in text


@pytest.mark.parametrize("name", COMMANDS)
def test_every_option_has_help(name: str) -> None:
    (sub,) = (a for a in build_parser()._actions if a.dest == "command")
    for action in sub.choices[name]._actions:
        assert action.help, f"{name} {'/'.join(action.option_strings)} has no help"


def test_simulate_shows_its_defaults(capsys) -> None:
    text = " ".join(command_help("simulate", capsys).split())  # unwrapped
    for shown in (
        "(default: robust)",
        "(default: 16)",
        "(default: static)",
        "(default: gen4-indoor)",
        "refresh index at the recording's start (default: 0)",
        "hand's path (default: 0)",
    ):
        assert shown in text


class OvershootingStream:
    """A reader whose position ends past the size it announced."""

    size = 1000
    position = 0

    def __iter__(self):
        for self.position in (400, 900, 1300):
            yield np.zeros(0)


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_the_progress_bar_stops_at_its_end(monkeypatch) -> None:
    terminal = Terminal()
    shown_at_once = functools.partial(tqdm, file=terminal, mininterval=0, miniters=1)
    monkeypatch.setattr("eventocc.receiver.commands.tqdm", shown_at_once)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        chunks = list(read_with_progress(OvershootingStream(), desc="x", quiet=False))
    assert len(chunks) == 3
    assert not [w for w in caught if "clamping frac" in str(w.message)]
    shown = terminal.getvalue()
    assert "1.00k/1.00k" in shown and "<-" not in shown, shown
