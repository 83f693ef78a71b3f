"""The virtual event camera: a screen showing the marker, a camera moving in front of it, and an
event sensor, with ground truth (poses, refresh times, payload bits)."""

from receiver.sim.display import Display
from receiver.sim.engine import Recording, simulate
from receiver.sim.motion import HandHeldMotion, StaticMotion, TumMotion
from receiver.sim.optics import Optics
from receiver.sim.scene import Scene
from receiver.sim.sensor import SensorModel

__all__ = [
    "Display",
    "HandHeldMotion",
    "Optics",
    "Recording",
    "Scene",
    "SensorModel",
    "StaticMotion",
    "TumMotion",
    "simulate",
]
