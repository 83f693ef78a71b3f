"""``eventocc-receiver info`` and ``convert``."""

from __future__ import annotations

import numpy as np

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
