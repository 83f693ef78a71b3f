"""``simulate(scene, duration_s)``: a streaming recording of the virtual event camera.

Iterating a ``Recording`` runs the simulation from the start (same seed, same events), one
``chunk_us`` window at a time, so memory stays bounded however long the recording is. Events
that fall past a window (sensor latency, or a still camera's refresh rendered whole) are held back
and merged into the next one.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from eventocc.receiver.events import EVENT_DTYPE, empty_events
from eventocc.receiver.sim.display import DisplayTimeline
from eventocc.receiver.sim.motion import image_box
from eventocc.receiver.sim.moving import MovingRenderer
from eventocc.receiver.sim.optics import centre_rays, rays_to_plane, sample_rays
from eventocc.receiver.sim.readout import Readout
from eventocc.receiver.sim.render import StaticRenderer
from eventocc.receiver.sim.scene import Scene
from eventocc.receiver.sim.sensor import BackgroundNoise, PixelArray, background_rates, to_events

_MARGIN_PX = 4.0
"""Pixels beyond the marker's outline that may still see it (blur, footprint); a sampled
point-spread function adds its reach."""


class Recording:
    def __init__(self, scene: Scene, duration_us: int, chunk_us: int) -> None:
        self.scene = scene
        self.duration_us = duration_us
        self.chunk_us = chunk_us
        self.trajectory = scene.motion.trajectory(scene.rig)
        self.made = 0
        """Events the pixels made in the latest run, before the readout stages."""
        self.readout: Readout | None = None
        """The latest run's readout stages, with what they delayed and dropped."""
        limit = getattr(self.trajectory, "duration_us", None)
        if limit is not None and duration_us > limit:
            raise ValueError(
                f"the trajectory lasts {limit / 1e6:.3f} s, shorter than the "
                f"requested {duration_us / 1e6:.3f} s"
            )

    @property
    def width(self) -> int:
        return self.scene.camera.width

    @property
    def height(self) -> int:
        return self.scene.camera.height

    def pose_at(self, t_us: np.ndarray) -> np.ndarray:
        """(n, 4, 4) ground-truth T_world_cam (marker frame) at event times ``t_us``."""
        return self.trajectory.pose_at(np.asarray(t_us) - self.scene.time_base_us)

    def refresh_times_us(self, k0: int, k1: int) -> np.ndarray:
        """Event times (us, float) at which refreshes ``k0 .. k1 - 1`` start scanning out (top
        row)."""
        s = self.scene
        period = s.display.period_us
        return (np.arange(k0, k1, dtype=np.float64) - s.first_refresh) * period + s.time_base_us

    def __iter__(self) -> Iterator[np.ndarray]:
        return _run(self)


def simulate(scene: Scene, duration_s: float, chunk_us: int = 10_000) -> Recording:
    """Events of ``scene`` over ``duration_s`` seconds, as a re-iterable stream of chunks."""
    if not duration_s > 0:
        raise ValueError(f"duration must be positive, got {duration_s} s")
    if chunk_us < 100:
        raise ValueError(f"chunk_us must be >= 100 us, got {chunk_us}")
    return Recording(scene, round(duration_s * 1e6), int(chunk_us))


def _run(rec: Recording) -> Iterator[np.ndarray]:
    scene, sensor, cam = rec.scene, rec.scene.sensor, rec.scene.camera
    # Spawned children do not depend on how many are spawned: the first three streams are
    # those of a scene without readout stages.
    rng_pixels, rng_noise, rng_delay, rng_readout = (
        np.random.default_rng(s) for s in np.random.SeedSequence(scene.seed).spawn(4)
    )
    rec.readout = readout = Readout(sensor, rng_readout)
    pixels = PixelArray.draw(sensor, cam.width * cam.height, rng_pixels)
    timeline = DisplayTimeline(scene.encoder, scene.display, scene.start_refresh, scene.lead_in)
    gain = scene.optics.gain(cam)
    renderer = _renderer(scene, rec, timeline, pixels, gain)
    rad = scene.radiometry
    intensity = np.full(cam.width * cam.height, rad.wall / rad.white)
    intensity[renderer.pix_index] = renderer.irradiance_now() / rad.white
    intensity *= gain  # the renderers' levels leave the vignetting out (``Optics.vignetting``)
    noise = BackgroundNoise(*background_rates(sensor, pixels, intensity))
    pending = empty_events()
    for t0 in range(0, rec.duration_us, rec.chunk_us):
        t1 = min(t0 + rec.chunk_us, rec.duration_us)
        signal = renderer.window(t0, t1)
        background = noise.events(t0, t1, rng_noise)
        t, i, p = (np.concatenate([a, b]) for a, b in zip(signal, background, strict=True))
        events = to_events(t, i, p, cam.width, sensor, rng_delay, pending)
        cut = int(np.searchsorted(events["t"], t1))
        pending = events[cut:] if t1 < rec.duration_us else empty_events()
        out = events[:cut]
        rec.made += len(out)
        if readout.active:
            out = readout.apply(out)
        chunk = np.ascontiguousarray(out, dtype=EVENT_DTYPE)
        if scene.time_base_us:
            # The readout works on the simulation's clock; the camera's starts elsewhere.
            # ``chunk`` may be a view of ``events``, apart from ``pending``.
            chunk["t"] += scene.time_base_us
        yield chunk


def _renderer(
    scene: Scene, rec: Recording, timeline: DisplayTimeline, pixels: PixelArray, gain: np.ndarray
):
    """The renderer for the scene's camera. A pixel's log level ``ln(g J + dark)`` (``g``: its
    ``gain``, the share of the scene's light ``J`` vignetting leaves) is rendered as
    ``ln(J + dark / g)``: the constant ``ln g`` between them fires no event."""
    sensor, cam = scene.sensor, scene.camera
    dark = scene.radiometry.dark / gain
    if not rec.trajectory.is_static:
        return MovingRenderer(
            scene, rec.trajectory, timeline, pixels, rec.chunk_us, rec.duration_us, dark
        )
    T = rec.trajectory.pose_at(np.zeros(1))[0]
    pix_index = _pixels_near_marker(scene, T)
    common = (
        scene.layout,
        timeline,
        scene.radiometry,
        pixels.threshold_on,
        pixels.threshold_off,
        sensor.refractory_us,
        sensor.photoreceptor_hz,
        dark[pix_index],
    )
    if scene.optics.psf_step_px is not None:
        offsets, weights = scene.optics.psf()
        offsets = offsets / cam.K[[0, 1], [0, 1]]  # to normalised ray units, as sample_offsets

        def points_of(idx: np.ndarray) -> np.ndarray:
            rays = centre_rays(cam, idx % cam.width, idx // cam.width)
            return rays_to_plane(rays[:, None, :] + offsets[None], T)

        return StaticRenderer(pix_index, points_of, *common, sample_weights=weights)
    rays = sample_rays(cam, scene.optics, pix_index % cam.width, pix_index // cam.width)
    return StaticRenderer(pix_index, rays_to_plane(rays, T), *common)


def _pixels_near_marker(scene: Scene, T_world_cam: np.ndarray) -> np.ndarray:
    """Flat indices of the pixels whose centre ray lands on the marker or just beside it."""
    cam = scene.camera
    reach = _MARGIN_PX
    if scene.optics.psf_step_px is not None:
        reach = max(reach, scene.optics.psf_reach_px + 1.0)
    x0, x1, y0, y1 = image_box(cam, T_world_cam, scene.rig.corners, 2 * reach)
    ys, xs = np.mgrid[y0:y1, x0:x1].reshape(2, -1)
    centre = rays_to_plane(centre_rays(cam, xs, ys), T_world_cam)
    depth = np.linalg.norm(T_world_cam[:3, 3] - scene.rig.centre)
    margin = reach * depth / cam.K[0, 0] * 2  # x2: oblique views stretch the footprint
    lo = scene.rig.corners[0, 0] - margin
    hi = scene.rig.corners[2, 0] + margin
    with np.errstate(invalid="ignore"):
        near = (
            (centre[:, 0] >= lo)
            & (centre[:, 0] <= hi)
            & (centre[:, 1] >= lo)
            & (centre[:, 1] <= hi)
        )
    return ys[near] * cam.width + xs[near]
