"""``eventocc-receiver info`` and ``convert``; every command's user errors."""

from __future__ import annotations

import numpy as np
import pytest

from eventocc.receiver.cli import main
from eventocc.receiver.events import concat, make_events
from eventocc.receiver.io import read_events, write_events

EVENTS = make_events(
    np.arange(0, 2_000_000, 1000),
    np.arange(2000) % 64,
    np.arange(2000) % 48,
    np.arange(2000) % 4 == 0,
)


def test_info_prints_the_summary(tmp_path, capsys):
    write_events(tmp_path / "a.raw", EVENTS, width=64, height=48)
    assert main(["info", "-q", str(tmp_path / "a.raw")]) == 0
    out = capsys.readouterr().out
    for expected in ("evt3", "64x48", "2,000", "1.999000 s", "25.0% ON"):
        assert expected in out


def test_convert_between_formats(tmp_path, capsys):
    write_events(tmp_path / "a.dat", EVENTS, width=64, height=48)
    assert (
        main(["convert", "-q", str(tmp_path / "a.dat"), str(tmp_path / "b.raw"), "--to", "evt2"])
        == 0
    )
    stream = read_events(tmp_path / "b.raw")
    assert (stream.format, stream.width) == ("evt2", 64)
    np.testing.assert_array_equal(concat(stream), EVENTS)
    assert "wrote 2,000 events" in capsys.readouterr().out


def _user_errors(tmp_path) -> list[tuple[list[str], str]]:
    """(arguments, what the one line says): a file, an option or a source a command cannot use."""
    text = tmp_path / "notes.txt"
    text.write_text("not events\n")
    write_events(tmp_path / "a.raw", EVENTS, width=64, height=48)
    out = str(tmp_path / "o.raw")
    return [
        (["info", "-q", str(tmp_path / "missing.raw")], "no such event file"),
        (["info", "-q", str(text)], "not 't x y p' text"),
        (["info", "-q", str(tmp_path)], "Is a directory"),
        (["info", "-q", "--format", "hdf5", str(text)], "not a readable HDF5 file"),
        (["convert", "-q", str(tmp_path / "missing.dat"), str(tmp_path / "o.raw")], "no such"),
        (["convert", "-q", str(text), out], "does not state its sensor"),
        (["convert", "-q", str(text), out, "--width", "9", "--height", "9"], "not 't x y p'"),
        (["convert", "-q", str(tmp_path / "a.raw"), str(tmp_path / "o.xyz")], "o.xyz"),
        (["decode", str(tmp_path / "missing.raw"), "--out", str(tmp_path / "d")], "--calibration"),
        (["simulate", "--message", str(tmp_path / "missing"), "--out", str(tmp_path)], "missing"),
        (["simulate", "--message", str(text), "--cells", "3", "--out", str(tmp_path)], "8..128"),
        (["receive", "--source", str(tmp_path / "missing.raw")], "no recording at"),
        (["receive", "--server", "http://127.0.0.1:9", "--cells", "3"], "8..128, got 3"),
        (["receive", "--server", "ftp://127.0.0.1:9"], "http(s) URL"),
    ]


@pytest.mark.parametrize("command", ["info", "convert", "decode", "simulate", "receive"])
def test_every_commands_user_errors_are_one_line(command: str, tmp_path, capsys):
    cases = [(args, says) for args, says in _user_errors(tmp_path) if args[0] == command]
    assert cases
    for args, says in cases:
        assert main(args) == 2, args
        err = capsys.readouterr().err.strip().splitlines()
        assert err[-1].startswith(f"eventocc-receiver {command}: error: "), (args, err)
        assert says in err[-1], (args, err)
        assert not any("Traceback" in line for line in err), (args, err)


def test_a_failed_convert_leaves_the_output_as_it_was(tmp_path, capsys):
    write_events(tmp_path / "a.dat", EVENTS, width=64, height=48)
    data = (tmp_path / "a.dat").read_bytes()
    (tmp_path / "cut.dat").write_bytes(data[: len(data) - 3])  # ends inside a record
    write_events(tmp_path / "out.raw", EVENTS[:10], width=64, height=48)
    before = (tmp_path / "out.raw").read_bytes()
    assert main(["convert", "-q", str(tmp_path / "cut.dat"), str(tmp_path / "out.raw")]) == 2
    assert "truncated" in capsys.readouterr().err
    assert (tmp_path / "out.raw").read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.dat", "cut.dat", "out.raw"]
