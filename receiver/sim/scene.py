"""Everything a simulation needs, in one JSON-able description."""

from __future__ import annotations

import base64
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from eventocc.occ.stream import StreamEncoder
from eventocc.receiver.camera import CameraModel
from eventocc.receiver.sim.display import (
    LUX_TO_NITS_PER_REFLECTANCE,
    Display,
    LeadIn,
    ScreenLayout,
)
from eventocc.receiver.sim.motion import Motion, Rig, StaticMotion, motion_from_dict
from eventocc.receiver.sim.optics import Optics
from eventocc.receiver.sim.render import Radiometry
from eventocc.receiver.sim.sensor import SensorModel


@dataclass(frozen=True, eq=False)
class Scene:
    encoder: StreamEncoder
    """What the screen shows."""
    marker_size_m: float = 0.272
    """Side of the white ring's outer boundary (the authors' default)."""
    display: Display = field(default_factory=Display)
    camera: CameraModel = field(default_factory=CameraModel.paper)
    motion: Motion = field(default_factory=StaticMotion)
    sensor: SensorModel = field(default_factory=lambda: SensorModel.preset("ideal"))
    optics: Optics = field(default_factory=Optics)
    wall_reflectance: float = 0.5
    """Diffuse reflectance of the wall around the screen (painted office wall)."""
    start_refresh: int = 0
    """The stream's first refresh on the screen (join the stream mid-way): its scan-out starts
    at t = 0, or where the lead-in ends."""
    lead_in: LeadIn = field(default_factory=LeadIn)
    """What the screen shows before the marker appears (nothing by default)."""
    time_base_us: int = 0
    """Event time of the simulation's t = 0: a camera's clock starts anywhere. Ground truth
    (``Recording.pose_at``, ``refresh_times_us``) is on the same clock."""
    seed: int = 0

    def __post_init__(self) -> None:
        if not self.marker_size_m > 0:
            raise ValueError(f"marker_size_m must be positive, got {self.marker_size_m}")
        if not 0 <= self.wall_reflectance <= 1:
            raise ValueError(f"wall_reflectance must be in [0, 1], got {self.wall_reflectance}")
        if self.start_refresh < 0:
            raise ValueError(f"start_refresh must be >= 0, got {self.start_refresh}")
        if self.time_base_us < 0:
            raise ValueError(f"time_base_us must be >= 0, got {self.time_base_us}")

    @property
    def first_refresh(self) -> int:
        """The display refresh whose scan-out starts at t = 0 (a lead-in's first)."""
        return self.start_refresh - self.lead_in.refreshes

    @property
    def marker_appears_us(self) -> float:
        """Event time at which the marker's first refresh starts scanning out (top row)."""
        return self.time_base_us + self.lead_in.refreshes * self.display.period_us

    @cached_property
    def layout(self) -> ScreenLayout:
        return ScreenLayout.of(self.encoder.geometry, self.marker_size_m, self.display)

    @cached_property
    def rig(self) -> Rig:
        geo, s = self.encoder.geometry, self.marker_size_m
        return Rig(self.camera, np.array([s / 2, s / 2, 0.0]), geo.marker_corners(s))

    @cached_property
    def radiometry(self) -> Radiometry:
        d, lux = self.display, self.sensor.lux
        ambient = d.ambient_nits(lux)
        return Radiometry(
            screen_ambient=ambient,
            screen_black=d.black_nits + ambient,
            wall=lux * self.wall_reflectance * LUX_TO_NITS_PER_REFLECTANCE,
            dark=self.sensor.dark_nits,
            white=d.peak_nits + ambient,
        )

    def cell_px(self) -> float:
        """Pixels per cell at the marker centre at t = 0 (the paper's 'pixels per cell')."""
        T = self.motion.trajectory(self.rig).pose_at(np.zeros(1))[0]
        depth = float((np.linalg.inv(T) @ np.append(self.rig.centre, 1.0))[2])
        return self.encoder.geometry.cell_size_m(self.marker_size_m) * self.camera.K[0, 0] / depth

    def describe(self) -> dict:
        enc, lay = self.encoder, self.layout
        return {
            "encoder": {
                "message_b64": base64.b64encode(enc.message).decode(),
                "name": enc.name,
                "profile": enc.profile.name,
                "cells": enc.geometry.cells,
                "ring": enc.geometry.ring,
                "preamble": enc.preamble_length > 0,
                "stream_id": enc.stream_id,
            },
            "marker_size_m": self.marker_size_m,
            "screen": {
                "side_m": lay.screen_side_m,
                "top_left_m": [lay.screen_top_m, lay.screen_top_m],
                "marker_top_fraction": lay.marker_top_fraction,
                "marker_height_fraction": lay.marker_height_fraction,
                "note": "square screen centred on the marker, in the marker frame; screen row v "
                "(0 top, 1 bottom) of refresh k switches at refresh_time(k) + v * "
                "scanout_fraction / refresh_hz",
            },
            "display": self.display.to_dict(),
            "camera": {
                "width": self.camera.width,
                "height": self.camera.height,
                "K": self.camera.K.tolist(),
                "dist": self.camera.dist.tolist(),
            },
            "motion": self.motion.to_dict(),
            "sensor": self.sensor.to_dict(),
            "optics": self.optics.to_dict(),
            "wall_reflectance": self.wall_reflectance,
            "start_refresh": self.start_refresh,
            "lead_in": self.lead_in.to_dict(),
            "time_base_us": self.time_base_us,
            "seed": self.seed,
            "cell_px": self.cell_px(),
        }

    @classmethod
    def from_dict(cls, d: dict) -> Scene:
        e = d["encoder"]
        encoder = StreamEncoder(
            base64.b64decode(e["message_b64"]),
            name=e["name"],
            profile=e["profile"],
            cells=e["cells"],
            ring=e["ring"],
            preamble=e["preamble"],
            stream_id=e["stream_id"],
        )
        cam = d["camera"]
        return cls(
            encoder=encoder,
            marker_size_m=d["marker_size_m"],
            display=Display.from_dict(d["display"]),
            camera=CameraModel(
                cam["width"], cam["height"], np.array(cam["K"]), np.array(cam["dist"])
            ),
            motion=motion_from_dict(d["motion"]),
            sensor=SensorModel.from_dict(d["sensor"]),
            optics=Optics(**d["optics"]),
            wall_reflectance=d["wall_reflectance"],
            start_refresh=d["start_refresh"],
            lead_in=LeadIn(**d.get("lead_in", {})),
            time_base_us=d.get("time_base_us", 0),
            seed=d["seed"],
        )


def marker_size_for_cell_px(cells_px: float, geometry, distance_m: float, focal_px: float) -> float:
    """Marker size (white ring's outer side) that shows ``cells_px`` pixels per cell at
    ``distance_m`` facing the camera."""
    return cells_px * geometry.tracked_side * distance_m / focal_px
