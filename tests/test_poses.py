import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from eventocc.receiver.poses import (
    TrajectoryFileError,
    format_seconds,
    invert,
    make_pose,
    read_tum,
    write_tum,
)


def test_tum_round_trip_keeps_microseconds(tmp_path):
    rng = np.random.default_rng(1)
    T = make_pose(Rotation.random(20, random_state=2).as_matrix(), rng.normal(size=(20, 3)))
    t_us = 1_700_000_000_000_000 + np.arange(20, dtype=np.int64) * 250  # epoch time, 4 kHz
    write_tum(tmp_path / "traj.txt", t_us, T)
    t_back, T_back = read_tum(tmp_path / "traj.txt")
    assert np.array_equal(t_back, t_us)
    assert np.allclose(T_back, T, atol=1e-8)


def test_invert_is_an_inverse():
    T = make_pose(Rotation.random(5, random_state=3).as_matrix(), np.arange(15.0).reshape(5, 3))
    assert np.allclose(invert(T) @ T, np.eye(4), atol=1e-12)


def test_format_seconds_is_exact():
    assert format_seconds(1_700_000_000_123_456) == "1700000000.123456"
    assert format_seconds(-5) == "-0.000005"


@pytest.mark.parametrize("line", ["0.1 1 2 3 0 0 0", "0.1 1 2 3 0 0 0 one"])
def test_bad_tum_rows_name_the_line(tmp_path, line):
    path = tmp_path / "bad.txt"
    path.write_text("# header\n" + line + "\n")
    with pytest.raises(TrajectoryFileError, match=r"bad.txt:2"):
        read_tum(path)
