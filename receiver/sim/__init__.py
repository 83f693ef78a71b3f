"""The virtual event camera: a screen showing the marker, a camera moving in front of it, and an
event sensor, with ground truth (poses, refresh times, payload bits)."""

from eventocc.receiver.sim.display import Display
from eventocc.receiver.sim.engine import Recording, simulate
from eventocc.receiver.sim.motion import HandHeldMotion, StaticMotion, TumMotion
from eventocc.receiver.sim.optics import Optics
from eventocc.receiver.sim.scene import Scene
from eventocc.receiver.sim.sensor import SensorModel

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
