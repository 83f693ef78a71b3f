"""The live camera backends against what their packages declare, without a camera:
neuromorphic-drivers' device protocols and packet classes, dv-processing's ``EventStore`` and
camera input classes (both installed by the ``dev`` extra), and the Metavision HAL facility
names the backend calls (the SDK is not on PyPI: checked against ``metavision_hal`` only where
it is installed). Each backend then runs on a device of that shape."""

from __future__ import annotations

import dataclasses
import inspect
import logging
import re
import sys
import types
import typing
from pathlib import Path

import neuromorphic_drivers as nd
import numpy as np
import pytest

from eventocc.occ.report import MessageReport
from eventocc.receiver.events import concat, make_events
from eventocc.receiver.io import read_events
from eventocc.receiver.live.cameras import METAVISION_FACILITIES, open_live_camera
from eventocc.receiver.live.controls import CameraSettings
from eventocc.receiver.live.daemon import Daemon, OutputFolder
from eventocc.receiver.live.nd_camera import POLARITY_DTYPE, NdCamera, NdDevice, configure
from eventocc.receiver.live.sources import SourceError
from tests.screen import SCREEN_MESSAGE, ReportSink, screen_receiver


def members(cls: type) -> set[str]:
    return {name for name in dir(cls) if not name.startswith("_")} | {"__next__", "__enter__"}


# --- neuromorphic-drivers: what the package declares ------------------------------------------
def test_the_nd_device_protocols_have_what_the_adapter_calls() -> None:
    used = {name for name in vars(NdDevice) if not name.startswith("_") or name == "__next__"}
    for protocol in (nd.GenericDevice, nd.prophesee_evk4.PropheseeEvk4Device):
        assert used <= members(protocol), f"{protocol.__name__} lacks {used - members(protocol)}"
    evk4 = members(nd.prophesee_evk4.PropheseeEvk4Device)
    assert {"temperature_celsius", "illuminance"} <= evk4
    assert list(inspect.signature(nd.GenericDevice.clear_backlog).parameters) == ["self", "until"]
    # The compiled device class: every method the protocols promise is really there.
    real = members(nd.device.Device)
    assert (used | {"temperature_celsius", "illuminance"}) <= real


def test_the_nd_packets_carry_polarity_events_and_their_overflow_indices() -> None:
    next_type = typing.get_type_hints(nd.prophesee_evk4.PropheseeEvk4Device.__next__)["return"]
    status_type, packet_type = typing.get_args(next_type)
    assert packet_type is nd.Evt3Packet and status_type is nd.status.StatusNonOptional
    for packet in (nd.Evt3Packet, nd.Davis346Packet, nd.DvxplorerPacket):
        fields = typing.get_type_hints(packet)
        assert {"polarity_events", "polarity_events_overflow_indices"} <= set(fields), packet
    ring = {f.name for f in dataclasses.fields(nd.status.RingStatus)}
    assert {"system_time", "backlog", "current_t", "dropped_packets"} <= ring
    assert callable(nd.status.Status.delay)


def test_the_evk4_configuration_takes_the_limiter_and_the_biases() -> None:
    device = ConfigurableDevice(nd.Name.PROPHESEE_EVK4)
    settings = CameraSettings(max_event_rate=20e6, rate_period_us=500, biases={"diff_on": 12})
    assert configure(device, settings) == 20e6
    (sent,) = device.sent
    assert isinstance(sent, nd.prophesee_evk4.Configuration)
    assert sent.rate_limiter == nd.prophesee_evk4.RateLimiter(500, 10_000)
    assert sent.biases == nd.prophesee_evk4.Biases(diff_on=12)
    sent.serialize()  # the package's own encoder accepts every field's type and range
    with pytest.raises(SourceError, match="no bias diff_up; its biases: pr, fo, hpf"):
        configure(device, CameraSettings(biases={"diff_up": 1}))
    with pytest.raises(SourceError, match=r"bias refr=99 is outside the camera's -20 \.\.\. 20"):
        configure(device, CameraSettings(biases={"refr": 99}))


def test_a_camera_without_a_limiter_gets_none_and_the_default_settings_change_nothing(
    caplog,
) -> None:
    davis = ConfigurableDevice(nd.Name.INIVATION_DAVIS346)
    with caplog.at_level(logging.INFO):
        assert configure(davis, CameraSettings()) is None
    assert davis.sent == [] and "has no event-rate limiter" in caplog.text
    evk4 = ConfigurableDevice(nd.Name.PROPHESEE_EVK4)
    assert configure(evk4, CameraSettings(max_event_rate=None)) is None and evk4.sent == []


class ConfigurableDevice:
    def __init__(self, name) -> None:
        self._name, self.sent = name, []

    def name(self):
        return self._name

    def biases_bounds(self):
        bounds = nd.prophesee_evk4.Bounds(-20, 20)
        return nd.prophesee_evk4.BiasesBounds(**dict.fromkeys(("diff_on", "refr"), bounds))

    def update_configuration(self, configuration) -> None:
        self.sent.append(configuration)


# --- neuromorphic-drivers: a device of the declared shape -------------------------------------
def packet(t, *, overflow_at=None) -> nd.Evt3Packet:
    """An ``Evt3Packet`` as the driver fills it (the package declares the class; its compiled
    twin has the same attributes)."""
    p = nd.Evt3Packet()
    p.polarity_events = np.zeros(len(t), POLARITY_DTYPE)
    p.polarity_events["t"] = t
    p.polarity_events["x"] = np.arange(len(t)) % 64
    p.polarity_events["y"] = 7
    p.polarity_events["on"] = np.arange(len(t)) % 2 == 0
    p.polarity_events_overflow_indices = None if overflow_at is None else np.array(overflow_at)
    p.trigger_events = p.trigger_events_overflow_indices = None
    return p


class ScriptedEvk4:
    """An EVK4 of ``PropheseeEvk4Device``'s shape replaying (delay in s, packet) pairs."""

    def __init__(self, script: list) -> None:
        self.script = iter(script)
        self.now = 1000.0  # the driver's wall clock: 10 ms per packet
        self.cleared: list[int] = []
        self.entered = self.exited = False

    def __enter__(self):
        self.entered = True
        return self

    def __exit__(self, *exc) -> bool:
        self.exited = True
        return False

    def __iter__(self):
        return self

    def __next__(self):
        delay, p = next(self.script)
        self.now += 0.01
        ring = nd.status.RingStatus(self.now - delay, 0, 1, False, 0, 0)
        return nd.status.Status(system_time=self.now, ring=ring), p

    def backlog(self) -> int:
        return 0

    def clear_backlog(self, until: int) -> None:
        self.cleared.append(until)

    def name(self):
        return nd.Name.PROPHESEE_EVK4

    def properties(self):
        return nd.prophesee_evk4.Properties()

    def biases_bounds(self):
        return nd.prophesee_evk4.BiasesBounds()

    def update_configuration(self, configuration) -> None:
        self.configuration = configuration

    def temperature_celsius(self) -> float:
        return 36.5

    def illuminance(self) -> int:
        return 812


def test_the_nd_backend_yields_the_polarity_events_of_the_packets(monkeypatch) -> None:
    """The regression: 0.18's packets are objects, where the backend read dicts only."""
    device = ScriptedEvk4([(0.001, packet([10, 20, 30])), (0.001, packet([40, 50]))])
    monkeypatch.setattr(nd, "open", lambda *args, **kwargs: device)
    camera = open_live_camera("nd")
    assert (camera.width, camera.height) == (1280, 720)
    chunks = list(camera.chunks())
    assert [c["t"].tolist() for c in chunks] == [[10, 20, 30], [40, 50]]
    assert chunks[0]["p"].tolist() == [1, -1, 1] and chunks[1]["x"].tolist() == [0, 1]
    assert device.entered and device.exited, "the device is closed when the stream ends"
    assert device.configuration.rate_limiter is not None, "the default limit is set"


def test_a_camera_that_stops_says_so() -> None:
    class Unplugged(ScriptedEvk4):
        def __next__(self):
            if next(self.count) == 1:
                raise RuntimeError("Disconnected")  # what the driver raises, as its message
            return super().__next__()

    device = Unplugged([(0.001, packet([10, 20]))])
    device.count = iter(range(2))
    chunks = NdCamera(device).chunks()
    assert next(chunks)["t"].tolist() == [10, 20]
    with pytest.raises(SourceError, match="the camera stopped: Disconnected"):
        next(chunks)
    assert device.exited, "and it is closed"


def test_usb_overflows_are_counted_with_the_event_time_they_lost(caplog) -> None:
    device = ScriptedEvk4(
        [
            (0.001, packet([100, 200, 300])),
            (0.001, packet([700, 800, 5_000, 5_100], overflow_at=[2])),  # 4.2 ms lost
            (0.001, packet([9_100, 9_200], overflow_at=[0])),  # lost since 5_100: 4 ms
        ]
    )
    camera = NdCamera(device)
    with caplog.at_level(logging.WARNING):
        assert sum(len(c) for c in camera.chunks()) == 9, "the events around a loss are kept"
    report = camera.camera_report()
    assert report.usb_overflows == 2 and report.usb_lost_s == pytest.approx(0.0082)
    assert (report.temperature_c, report.illuminance, report.illuminance_unit) == (
        36.5,
        812,
        "count",
    )
    assert report.max_event_rate == 100e6
    assert "USB ring overflowed 1 time(s)" in caplog.text, "said once, not every packet"


def test_a_receiver_behind_skips_the_drivers_backlog_undecoded(caplog) -> None:
    """A packet that arrived more than a second ago: the backlog goes, undecoded, in the
    driver; the receiver sees the gap and the share of the events it kept."""
    script = [(0.01, packet(np.arange(k * 10_000, (k + 1) * 10_000, 100))) for k in range(250)]
    script[120] = (1.5, script[120][1])  # the receiver fell behind here
    device = ScriptedEvk4(script)
    camera = NdCamera(device, window_s=1.0)
    with caplog.at_level(logging.WARNING):
        kept = list(camera.chunks())
    assert device.cleared == [0] and camera.skips == 1
    assert len(kept) == 249 and int(kept[120]["t"][0]) == 1_210_000
    assert camera.speed == pytest.approx(0.99, abs=0.005), "one 10 ms packet of ~1 s was lost"
    assert "skipped ahead 1 time(s)" in caplog.text


# --- dv-processing --------------------------------------------------------------------------
def test_dv_processing_declares_what_the_dv_backend_reads() -> None:
    import dv_processing as dv

    store = dv.EventStore()
    store.push_back(1000, 3, 4, True)
    assert set(store.numpy().dtype.names) >= {"timestamp", "x", "y", "polarity"}
    for name in ("getEventResolution", "getNextEventBatch", "isRunning"):
        assert hasattr(dv.io.camera.CameraInputBase, name)
        assert hasattr(dv.io.MonoCameraRecording, name), "a recording is a camera input too"
    doc = dv.io.camera.CameraInputBase.getNextEventBatch.__doc__
    assert "-> dv_processing.EventStore | None" in doc
    assert callable(dv.io.camera.open)


def test_the_dv_backend_refuses_biases_it_cannot_set() -> None:
    with pytest.raises(SourceError, match="sets no biases"):
        open_live_camera("dv", "", CameraSettings(biases={"diff": 1}))


# --- Metavision (not on PyPI) ---------------------------------------------------------------
class MetavisionDevice:
    """A HAL device with the facilities ``METAVISION_FACILITIES`` names, and nothing else."""

    def __init__(self) -> None:
        self.calls: list[tuple] = []
        facility = self

        class Facility:
            def __init__(self, methods) -> None:
                for method in methods:
                    setattr(self, method, self._recorder(method))

            @staticmethod
            def _recorder(method):
                def call(*args):
                    facility.calls.append((method, *args))
                    return {
                        "get_all_biases": {"bias_diff_on": 0, "bias_fo": 0},
                        "get_temperature": 41,
                        "get_illumination": 250,
                        "set": True,
                    }.get(method)

                return call

        for getter, methods in METAVISION_FACILITIES.items():
            setattr(self, getter, lambda methods=methods: Facility(methods))


def test_the_metavision_controls_use_only_the_hal_names_it_declares() -> None:
    from eventocc.receiver.live.cameras import _metavision_controls

    device = MetavisionDevice()
    settings = CameraSettings(max_event_rate=50e6, biases={"diff_on": 5, "bias_fo": -3})
    assert _metavision_controls(device, settings) == 50e6
    assert device.calls == [
        ("set_cd_event_rate", 50_000_000),
        ("enable", True),
        ("get_all_biases",),
        ("set", "bias_diff_on", 5),
        ("set", "bias_fo", -3),
    ]
    with pytest.raises(SourceError, match="no bias hpf; its biases: bias_diff_on, bias_fo"):
        _metavision_controls(device, CameraSettings(biases={"hpf": 1}))


def test_the_metavision_names_match_the_installed_hal() -> None:
    hal = pytest.importorskip("metavision_hal", reason="Metavision's SDK is not on PyPI")
    for getter, methods in METAVISION_FACILITIES.items():
        # pybind11 states the facility a getter returns in its signature line.
        returned = re.search(r"-> metavision_hal\.(\w+)", getattr(hal.Device, getter).__doc__)
        assert returned is not None, getter
        facility = getattr(hal, returned.group(1))
        assert all(hasattr(facility, m) for m in methods), (getter, methods)


def test_the_event_arrays_the_backends_build_are_ours() -> None:
    events = np.zeros(3, POLARITY_DTYPE)
    events["t"], events["on"] = [5, 6, 7], [True, False, True]
    built = make_events(events["t"].astype(np.int64), events["x"], events["y"], events["on"])
    assert built["p"].tolist() == [1, -1, 1] and built["t"].dtype == np.int64


# --- each backend through the daemon into a decoded message ---------------------------------
def head(recording: Path, seconds: float) -> np.ndarray:
    events = concat(read_events(recording / "events.raw"))
    return events[events["t"] < seconds * 1e6]


def decoded_through_the_daemon(source, tmp_path: Path) -> list[bytes]:
    sink = ReportSink()
    Daemon(source, screen_receiver(), sink, OutputFolder(tmp_path / "out")).run()
    return [m.data for m in sink.of(MessageReport)]


def test_the_dv_backend_on_dv_processings_own_input_decodes_the_message(
    screen_recording, tmp_path, monkeypatch
) -> None:
    """The camera: dv-processing's recording reader, an input of the same declared class as
    its cameras (``InputBase``), on the recording written by its own writer."""
    import dv_processing as dv

    store = dv.EventStore()
    for t, x, y, p in head(screen_recording, 1.0).tolist():
        store.push_back(t, x, y, p > 0)
    path = str(tmp_path / "screen.aedat4")
    writer = dv.io.MonoCameraWriter(path, dv.io.MonoCameraWriter.EventOnlyConfig("DVX", (320, 180)))
    writer.writeEvents(store)
    del writer  # closes the file
    monkeypatch.setattr(dv.io.camera, "open", lambda *args: dv.io.MonoCameraRecording(path))
    camera = open_live_camera("dv")
    assert (camera.width, camera.height) == (320, 180)
    assert decoded_through_the_daemon(camera, tmp_path) == [SCREEN_MESSAGE]


def test_the_metavision_backend_on_a_device_of_the_hals_shape_decodes_the_message(
    screen_recording, tmp_path, monkeypatch
) -> None:
    """Metavision's SDK is not on PyPI: its modules here are stand-ins with the names the
    backend imports and the array layout its documentation gives (x, y, p, t)."""
    events = head(screen_recording, 1.0)
    layout = np.dtype([("x", "<u2"), ("y", "<u2"), ("p", "<i2"), ("t", "<i8")])

    class EventsIterator:
        @classmethod
        def from_device(cls, device, delta_t):
            iterator = cls()
            iterator.delta_t = delta_t
            return iterator

        def get_size(self):
            return 180, 320

        def __iter__(self):
            for start in range(0, int(events["t"][-1]) + 1, self.delta_t):
                window = events[(events["t"] >= start) & (events["t"] < start + self.delta_t)]
                out = np.empty(len(window), layout)
                for name in ("x", "y", "t"):
                    out[name] = window[name]
                out["p"] = window["p"] > 0
                yield out

    device = MetavisionDevice()
    event_io = types.ModuleType("metavision_core.event_io")
    event_io.EventsIterator = EventsIterator
    raw_reader = types.ModuleType("metavision_core.event_io.raw_reader")
    raw_reader.initiate_device = lambda path: device
    monkeypatch.setitem(sys.modules, "metavision_core", types.ModuleType("metavision_core"))
    monkeypatch.setitem(sys.modules, "metavision_core.event_io", event_io)
    monkeypatch.setitem(sys.modules, "metavision_core.event_io.raw_reader", raw_reader)
    camera = open_live_camera("metavision")
    assert decoded_through_the_daemon(camera, tmp_path) == [SCREEN_MESSAGE]
    report = camera.camera_report()
    assert (report.temperature_c, report.illuminance, report.illuminance_unit) == (41, 250, "lux")
    assert ("set_cd_event_rate", 100_000_000) in device.calls
