"""A live camera's own controls: what the receiver sets on it (its event-rate limiter and its
biases) and what it reads from it (temperature and illuminance, for the dashboard).

The settings come from the receive command's options or a camera config file (YAML):

    max_event_rate: 100e6    # events/s the sensor lets through; null turns the limiter off
    rate_period_us: 1000     # the limiter's counting period
    biases: {diff_on: 10, diff_off: 10}   # names and units as the camera's driver has them

Each backend applies what its camera has, and says what it cannot apply.
"""

from __future__ import annotations

import argparse
import logging
import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from types import MappingProxyType
from typing import Any

import yaml

from eventocc.occ.report import CameraReport
from eventocc.receiver.live.sources import SourceError

log = logging.getLogger(__name__)

DEFAULT_MAX_EVENT_RATE = 100e6
"""Events/s a camera watching a screen is let send by default. A marker filling a 1280x720 view
makes 18 M events/s on a tripod and 67 M hand-held at 0.6 m (the simulator, docs/BENCHMARKS.md);
this clips only storms beyond them (a flickering backlight, the whole field changing at once),
which would overrun the USB link and the receiver alike."""
DEFAULT_RATE_PERIOD_US = 1000
READINGS_EVERY_S = 1.0
"""A temperature or light reading is a register read over USB: once a second is plenty."""


@dataclass(frozen=True)
class CameraSettings:
    max_event_rate: float | None = DEFAULT_MAX_EVENT_RATE
    """Events per second the sensor's own limiter lets through (None: no limit)."""
    rate_period_us: int = DEFAULT_RATE_PERIOD_US
    """The limiter counts events over periods of this length."""
    biases: Mapping[str, int] = field(default_factory=dict)
    """Bias name -> value, in the driver's names and units; unnamed biases keep its defaults."""

    def __post_init__(self) -> None:
        rate = self.max_event_rate
        if rate is not None and not (math.isfinite(rate) and rate > 0):
            raise SourceError(f"max_event_rate must be a positive number of events/s, got {rate}")
        if not 1 <= self.rate_period_us <= 65_535:
            raise SourceError(f"rate_period_us must be 1 ... 65535, got {self.rate_period_us}")
        if rate is not None and self.events_per_period < 1:
            raise SourceError(
                f"max_event_rate {rate:g}/s allows no event in {self.rate_period_us} us: "
                "raise it or the period"
            )
        object.__setattr__(self, "biases", MappingProxyType(dict(self.biases)))

    @property
    def events_per_period(self) -> int:
        """The limit as the sensors' limiters take it: events per counting period."""
        assert self.max_event_rate is not None
        return int(self.max_event_rate * self.rate_period_us / 1e6)

    @property
    def rate_in_force(self) -> float:
        """Events/s the limiter lets through: ``max_event_rate`` in whole events per period."""
        return self.events_per_period * 1e6 / self.rate_period_us


def load_camera_settings(path: Path) -> CameraSettings:
    """A camera config file (the module docstring's keys, each optional)."""
    try:
        doc = yaml.safe_load(path.read_text()) or {}
    except (OSError, yaml.YAMLError) as error:
        raise SourceError(f"camera config {path}: cannot read it ({error})") from None
    if not isinstance(doc, dict):
        raise SourceError(f"camera config {path}: expected a mapping of settings")
    known = {"max_event_rate", "rate_period_us", "biases"}
    if unknown := sorted(set(doc) - known):
        raise SourceError(
            f"camera config {path}: unknown setting(s) {', '.join(unknown)}; "
            f"use {', '.join(sorted(known))}"
        )
    biases = doc.get("biases") or {}
    if not isinstance(biases, dict) or not all(_is_int(v) for v in biases.values()):
        raise SourceError(f"camera config {path}: biases must map names to whole numbers")
    rate = _number(doc.get("max_event_rate", DEFAULT_MAX_EVENT_RATE))
    period = doc.get("rate_period_us", DEFAULT_RATE_PERIOD_US)
    if not (rate is None or _is_number(rate)) or not _is_int(period):
        raise SourceError(
            f"camera config {path}: max_event_rate must be a number or null, "
            "rate_period_us a whole number"
        )
    return CameraSettings(
        None if rate is None else float(rate), int(period), {str(k): v for k, v in biases.items()}
    )


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _number(value: Any) -> Any:
    """YAML 1.1 reads ``20e6`` (no dot, no sign) as a string: take it as the number it says."""
    try:
        return float(value) if isinstance(value, str) else value
    except ValueError:
        return value


def _is_number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def add_camera_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group(
        "live camera controls", "applied where the camera has them (default: its own biases)"
    )
    group.add_argument(
        "--camera-config", type=Path, help="YAML file: max_event_rate, rate_period_us, biases"
    )
    group.add_argument(
        "--max-event-rate",
        type=float,
        metavar="EV_PER_S",
        help=f"the sensor's own event-rate limit, events/s; 0 turns it off "
        f"(default {DEFAULT_MAX_EVENT_RATE:g})",
    )
    group.add_argument(
        "--bias",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="set one bias, in the driver's names and units (repeatable)",
    )


def camera_settings(args: argparse.Namespace) -> CameraSettings:
    """The settings of ``add_camera_arguments``' options: the file's, then each option's."""
    settings = CameraSettings()
    if args.camera_config is not None:
        settings = load_camera_settings(args.camera_config)
    if args.max_event_rate is not None:
        settings = replace(settings, max_event_rate=args.max_event_rate or None)
    if args.bias:
        settings = replace(settings, biases={**settings.biases, **_parse_biases(args.bias)})
    return settings


def _parse_biases(items: list[str]) -> dict[str, int]:
    biases = {}
    for item in items:
        name, _, value = item.partition("=")
        if not name.strip() or not value.strip().lstrip("+-").isdigit():
            raise SourceError(f"--bias {item!r}: write NAME=VALUE with a whole number")
        biases[name.strip()] = int(value)
    return biases


class SensorReadings:
    """Polls a camera's temperature and illuminance at most every ``READINGS_EVERY_S``; a
    reading the camera refuses (not implemented, a failed measurement) is dropped for good."""

    def __init__(
        self,
        temperature_c: Callable[[], float] | None,
        illuminance: Callable[[], float] | None,
        illuminance_unit: str,
        *,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._read = {"temperature_c": temperature_c, "illuminance": illuminance}
        self._unit = illuminance_unit
        self._clock = clock
        self._next = -math.inf
        self.values: dict[str, float] = {}

    def poll(self) -> None:
        if self._clock() < self._next:
            return
        self._next = self._clock() + READINGS_EVERY_S
        for name, read in list(self._read.items()):
            if read is None:
                continue
            try:
                self.values[name] = float(read())
            except Exception as error:  # drivers raise their own errors, or RuntimeError
                log.info("the camera gives no %s (%s): not asked again", name, error)
                self._read[name] = None
                self.values.pop(name, None)

    def report(self, **counts: Any) -> CameraReport:
        lux = self.values.get("illuminance")
        return CameraReport(
            temperature_c=self.values.get("temperature_c"),
            illuminance=lux,
            illuminance_unit=None if lux is None else self._unit,
            **counts,
        )
