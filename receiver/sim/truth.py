"""What a simulated scene's screen sent, as the receiver's scorers take it."""

from __future__ import annotations

import numpy as np

from eventocc.receiver.pipeline.report import FrameTruth
from eventocc.receiver.sim.scene import Scene


class SceneTruth(FrameTruth):
    """``FrameTruth`` of a scene on its recording's clock: refresh ``scene.first_refresh``
    (a lead-in's first) scans out at the scene's time base."""

    def __init__(self, scene: Scene) -> None:
        super().__init__(scene.encoder, scene.display.refresh_hz, scene.first_refresh)
        self.time_base_us = scene.time_base_us

    def errors(self, bits: np.ndarray, t_us: int) -> int | None:
        return super().errors(bits, t_us - self.time_base_us)
