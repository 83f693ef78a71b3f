"""What the evk4 preset adds to the virtual camera: photoreceptor lag, a sampled lens PSF and the
readout's limits, each against the number it claims."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from eventocc.receiver.events import EVENT_DTYPE, concat
from eventocc.receiver.sim import Display, HandHeldMotion, Optics, SensorModel, simulate
from eventocc.receiver.sim.readout import Readout
from eventocc.receiver.sim.sensor import PHOTORECEPTOR_REF_NITS
from tests.test_sim_physics import OLED, SMALL, small_scene

SHARP = Optics(blur_px=0.0, supersample=1)


def test_the_photoreceptor_lags_a_step_as_a_low_pass_at_its_light():
    """A black-to-white step through a first-order low-pass of the log irradiance whose time
    constant is set by the light: the n-th ON event comes tau ln(D / (D - n C)) after the
    switch, where D is the step in ln units, C the threshold and tau = 1 / (2 pi f) at white."""
    f = 500.0
    sensor = replace(SensorModel.preset("ideal"), photoreceptor_hz=f)
    scene = small_scene(display=OLED, optics=SHARP, sensor=sensor)
    instant = events_of(small_scene(display=OLED, optics=SHARP), 0.016)
    lagged = events_of(scene, 0.016)
    rad = scene.radiometry
    white = rad.white + rad.dark
    step = math.log(white / (rad.screen_black + rad.dark))
    tau = PHOTORECEPTOR_REF_NITS / white / (2 * math.pi * f) * 1e6
    count = math.floor(step / 0.2)
    expected = tau * np.log(step / (step - 0.2 * np.arange(1, count + 1)))
    switch = _first_on(instant)
    checked = 0
    for pix, t in _on_times(lagged).items():
        if pix not in switch or len(t) != count:
            continue
        assert np.abs(t - switch[pix] - expected).max() <= 1.0  # microsecond rounding
        checked += 1
    assert checked > 100
    assert expected[-1] > 3 * tau  # the lag is there to see


def test_the_photoreceptor_is_refused_where_it_is_not_simulated():
    sensor = replace(SensorModel.preset("ideal"), photoreceptor_hz=500.0)
    with pytest.raises(ValueError, match="still cameras only"):
        list(simulate(small_scene(sensor=sensor, motion=HandHeldMotion(3.0, 0.5)), 0.01))
    with pytest.raises(ValueError, match="PWM backlight"):
        list(simulate(small_scene(sensor=sensor, display=Display.oled()), 0.01))


def test_the_sampled_psf_holds_the_light_of_aperture_blur_and_defocus():
    optics = Optics(blur_px=0.7, defocus_px=0.65, psf_step_px=0.5)
    offsets, weights = optics.psf()
    assert weights.sum() == pytest.approx(1.0)
    # Per axis: the pixel's square aperture (1/12), the Gaussian, the disk (D² / 16), and the
    # binning on the grid (step² / 12).
    variance = 1 / 12 + 0.7**2 + 0.65**2 / 16 + 0.5**2 / 12
    assert weights @ offsets[:, 0] ** 2 == pytest.approx(variance, rel=0.03)
    assert weights @ offsets[:, 1] ** 2 == pytest.approx(variance, rel=0.03)
    assert np.abs(offsets).max() <= optics.psf_reach_px + 0.25
    # Its tail reaches well beyond the variance-matched footprint's outermost ray.
    assert np.abs(offsets).max() > 2 * np.abs(replace(optics, psf_step_px=None).offsets()).max()


def test_a_still_camera_sees_the_psf_tail_in_a_black_cell_next_to_white():
    """A wide PSF lights black cells' pixels from white neighbours: more pixels fire than with
    the sharp footprint, and the scene still keeps its events in time order."""
    sharp = events_of(small_scene(display=OLED), 0.016)
    wide = Optics(blur_px=1.5, psf_step_px=0.5)
    blurred = events_of(small_scene(display=OLED, optics=wide), 0.016)
    fired = lambda ev: len(np.unique(ev["y"].astype(np.int64) * SMALL.width + ev["x"]))  # noqa: E731
    assert fired(blurred) > 1.1 * fired(sharp)
    assert np.diff(blurred["t"]).min() >= 0


def _events(t_us: np.ndarray) -> np.ndarray:
    ev = np.zeros(len(t_us), EVENT_DTYPE)
    ev["t"] = t_us
    ev["x"], ev["y"] = np.arange(len(t_us)) % 1024, np.arange(len(t_us)) // 1024  # an event id
    ev["p"] = 1
    return ev


def _readout(**kw) -> Readout:
    return Readout(replace(SensorModel.preset("ideal"), **kw), np.random.default_rng(0))


def test_the_rate_controller_keeps_its_budget_in_each_period_and_no_less():
    readout = _readout(erc_hz=1e6, erc_period_us=1000)  # 1000 events per period
    busy = np.sort(np.random.default_rng(1).integers(0, 1000, 5000))
    quiet = np.sort(np.random.default_rng(2).integers(1000, 2000, 400))
    out = readout.apply(_events(np.concatenate([busy, quiet])))
    assert np.count_nonzero(out["t"] < 1000) == 1000
    assert np.count_nonzero(out["t"] >= 1000) == 400
    assert readout.dropped_erc == 4000
    # Evenly: the kept events of the busy period span it.
    assert out["t"][:1000].min() < 50 and out["t"][:1000].max() > 950


def test_the_link_loses_events_only_beyond_its_rate_and_buffer_and_evenly_over_the_view():
    readout = _readout(link_hz=10e6, link_buffer=500)  # 10 events per microsecond
    slow = _events(np.repeat(np.arange(0, 1000), 8))  # 8 per microsecond: all carried
    assert len(readout.apply(slow)) == len(slow)
    fast = _events(np.repeat(np.arange(1000, 3000), 20))  # twice the link
    out = readout.apply(fast)
    carried = len(out)
    # The buffer fills, then the link's rate gets through: half the events, plus the buffer.
    assert carried == pytest.approx(10 * 2000 + 500, rel=0.02)
    assert readout.dropped_link == len(fast) - carried
    # The events of one microsecond come packed in row order; a full buffer still thins the
    # last of them as much as the first (the bottom of the view as much as its top).
    kept = np.zeros(len(fast), bool)
    kept[out["y"].astype(np.int64) * 1024 + out["x"]] = True
    by_rank = kept[1000:].reshape(-1, 20).mean(axis=0)  # once the buffer is full
    assert by_rank.min() > 0.4 and by_rank.max() < 0.6
    # The surviving events keep their sensor timestamps.
    assert np.isin(out["t"], fast["t"]).all()


def test_the_sensor_readout_delays_a_burst_but_keeps_every_event_in_order():
    readout = _readout(readout_hz=1e8)  # one event per 10 ns
    burst = _events(np.full(2000, 100))
    out = readout.apply(burst)
    assert len(out) == len(burst)
    assert out["t"].min() == 100 and out["t"].max() == 100 + 20  # 2000 events x 10 ns
    assert np.diff(out["t"]).min() >= 0
    # The next window's events queue behind the burst's tail.
    later = readout.apply(_events(np.array([105, 130])))
    assert later["t"][0] >= 120 and later["t"][1] == 130


def test_without_readout_stages_every_event_made_is_delivered():
    rec = simulate(small_scene(sensor=SensorModel.preset("gen4-indoor")), 0.02)
    assert sum(len(c) for c in rec) == rec.made > 0
    assert rec.readout is not None and not rec.readout.active


def test_evk4_delivers_no_more_than_its_link_and_counts_what_it_dropped():
    sensor = replace(SensorModel.preset("evk4"), link_hz=5e6, link_buffer=5000)
    rec = simulate(small_scene(sensor=sensor, optics=Optics.preset("evk4")), 0.05)
    delivered = sum(len(c) for c in rec)
    assert delivered <= 5e6 * 0.05 + 5000
    dropped = rec.readout.dropped_erc + rec.readout.dropped_link
    assert delivered + dropped == rec.made > delivered


@pytest.mark.parametrize(
    "fields, message",
    [
        ({"link_hz": 1e6, "link_buffer": 0}, "buffer of at least one event"),
        ({"erc_hz": 100.0}, "lets no event through"),
        ({"readout_hz": 0.0}, "readout_hz must be positive"),
        ({"photoreceptor_hz": -1.0}, "photoreceptor_hz must be >= 0"),
    ],
)
def test_bad_readout_settings_are_refused(fields, message):
    with pytest.raises(ValueError, match=message):
        replace(SensorModel.preset("evk4"), **fields)


def events_of(scene, duration_s: float) -> np.ndarray:
    return concat(simulate(scene, duration_s))


def _on_times(ev: np.ndarray) -> dict[int, np.ndarray]:
    on = ev[ev["p"] > 0]
    pix = on["y"].astype(np.int64) * SMALL.width + on["x"]
    order = np.argsort(pix, kind="stable")
    pix, t = pix[order], on["t"][order].astype(float)
    starts = np.flatnonzero(np.r_[True, pix[1:] != pix[:-1]])
    return {int(pix[s]): t[s:e] for s, e in zip(starts, np.r_[starts[1:], len(pix)], strict=True)}


def _first_on(ev: np.ndarray) -> dict[int, float]:
    return {pix: float(t.min()) for pix, t in _on_times(ev).items()}


def test_the_realistic_bench_fits_the_marker_and_can_lift_the_readout_limits():
    from bench.realistic import FIT_SHARE, NO_READOUT, cells_for, sensor_for
    from eventocc.occ.marker import MarkerGeometry

    for px in (4, 7, 13, 30):
        n = cells_for(px)
        assert MarkerGeometry(n).tracked_side * px <= FIT_SHARE * 720
        assert n == 128 or MarkerGeometry(n + 8).tracked_side * px > FIT_SHARE * 720
    lifted = sensor_for("evk4" + NO_READOUT)
    assert (lifted.readout_hz, lifted.erc_hz, lifted.link_hz) == (None, None, None)
    assert lifted.photoreceptor_hz == SensorModel.preset("evk4").photoreceptor_hz


def test_the_authors_reader_counts_a_cell_by_its_recent_on_events_over_its_whole_area():
    from bench.authors_reader import SurfaceReader

    # A 4 x 4 grid of 10 px cells at (10, 10)-(50, 50) of a 60 x 60 sensor.
    corners = np.array([[10.0, 10.0], [50.0, 10.0], [50.0, 50.0], [10.0, 50.0]])
    reader = SurfaceReader(corners, 4, (60, 60))
    ys, xs = np.mgrid[20:30, 30:40]  # the whole cell of row 1, column 2
    lit = np.zeros(xs.size, EVENT_DTYPE)
    lit["x"], lit["y"], lit["t"], lit["p"] = xs.ravel(), ys.ravel(), 10_000, 1
    stale = np.zeros(100, EVENT_DTYPE)  # row 3, column 0, long before
    stale["x"], stale["y"], stale["t"], stale["p"] = xs.ravel() - 20, ys.ravel() + 20, 100, 1
    ys0, xs0 = np.mgrid[10:20, 10:20]  # row 0, column 0: its outer two pixels, as spill fires
    ring = (np.minimum(xs0 - 10, 19 - xs0) < 2) | (np.minimum(ys0 - 10, 19 - ys0) < 2)
    border = np.zeros(int(ring.sum()), EVENT_DTYPE)
    border["x"], border["y"], border["t"], border["p"] = xs0[ring], ys0[ring], 10_000, 1
    off = lit.copy()
    off["x"] -= 10  # row 1, column 1: OFF events only
    off["p"] = -1
    reader.feed(np.concatenate([stale, border, lit, off]))
    # 64% of the border cell fired: the whole-cell rule reads it 1, its inner part 0.
    assert np.argwhere(reader.cells(3_000.0)).tolist() == [[0, 0], [1, 2]]
    assert np.argwhere(reader.cells(3_000.0, margin=0.2)).tolist() == [[1, 2]]
