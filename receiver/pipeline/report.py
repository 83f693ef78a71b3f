"""What a decoding run produced: poses, frames, messages, and the JSON report about them.

``pushes`` is the one decode loop (every chunk pushed, then the finish) that the CLI, the
benchmarks and the tests share; ``decode_events`` collects what it gives into a ``DecodeLog``,
which with a ``FrameTruth`` (from a simulator scene) also scores every frame's bits against what
the screen really showed, and every message against the bytes really sent.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np

from eventocc.receiver.pipeline.metrics import best_alignment
from eventocc.receiver.pipeline.receiver import (
    FrameOutput,
    MessageOutput,
    Output,
    PoseEstimate,
    Receiver,
    StateChange,
)
from eventocc.receiver.poses import write_tum


class FrameTruth:
    """What the screen sent around a time, for BER. Receiver frame indices are relative, so each
    read frame is matched to the closest of the refreshes near its time; frames matched to a
    refresh that carries no symbol (``fast``'s key refreshes) are not scored."""

    def __init__(self, encoder, refresh_hz: float, start_refresh: int = 0) -> None:
        self.encoder = encoder
        self.refresh_hz = refresh_hz
        self.start_refresh = start_refresh

    def sent(self, k: int) -> np.ndarray:
        """The bits a receiver reads at refresh ``k``: the payload shown, or for ``fast`` the
        cells that toggled (every refresh, key refreshes included)."""
        shown = self._shown(k)
        if self.encoder.profile.data_every == 1:
            return shown ^ self._shown(k - 1)
        return shown

    def _shown(self, k: int) -> np.ndarray:
        """The payload cells of refresh ``k``; blank before the stream's first, as the screen
        shows them (``eventocc.receiver.sim.display``)."""
        geo = self.encoder.geometry
        return geo.payload_of(self.encoder.frame(k) if k >= 0 else geo.blank_frame)

    def errors(self, bits: np.ndarray, t_us: int) -> int | None:
        """Bit errors of a frame read at ``t_us``, or None if it matches no data refresh."""
        matched = self.match(bits, t_us)
        return None if matched is None else matched[1]

    def match(self, bits: np.ndarray, t_us: int) -> tuple[int, int] | None:
        """(refresh, bit errors) of the data refresh a frame read at ``t_us`` matches best, or
        None if it matches no data refresh."""
        k = self.start_refresh + int(np.floor(t_us * self.refresh_hz / 1e6))
        ks = list(range(max(0, k - 2), k + 2))
        if self.encoder.profile.data_every == 2:
            ks = [j for j in ks if self.encoder.is_data_frame(j)]
        if not ks:
            return None
        i, errors = best_alignment(bits, [self.sent(j) for j in ks])
        return (ks[i], errors) if self.encoder.is_data_frame(ks[i]) else None

    def data_refreshes(self, from_us: int, to_us: int) -> list[int]:
        """The data refreshes shown whole between ``from_us`` and ``to_us`` (stream time, as
        the frames' ``t_us``)."""
        period_us = 1e6 / self.refresh_hz
        first = self.start_refresh + math.ceil(from_us / period_us)
        last = self.start_refresh + math.floor(to_us / period_us) - 1
        return [k for k in range(max(first, 0), last + 1) if self.encoder.is_data_frame(k)]


class DecodeLog:
    def __init__(self, receiver: Receiver, truth: FrameTruth | None = None) -> None:
        self.receiver = receiver
        self.truth = truth
        self.pose_t: list[int] = []
        self.poses: list[np.ndarray] = []
        self.pose_verified: list[bool] = []
        self.messages: list[MessageOutput] = []
        self.states: list[StateChange] = []
        self.frames = 0
        self.bits = 0
        self.bit_errors = 0

    def add(self, outputs: list[Output]) -> None:
        for o in outputs:
            if isinstance(o, PoseEstimate):
                self.pose_t.append(o.t_us)
                self.poses.append(o.T_world_cam)
                self.pose_verified.append(o.verified)
            elif isinstance(o, FrameOutput) and o.accepted:
                self.frames += 1
                errors = None if self.truth is None else self.truth.errors(o.read.bits, o.read.t_us)
                if errors is not None:
                    self.bits += o.read.bits.size
                    self.bit_errors += errors
            elif isinstance(o, MessageOutput):
                self.messages.append(o)
            elif isinstance(o, StateChange):
                self.states.append(o)

    @property
    def ber(self) -> float | None:
        return self.bit_errors / self.bits if self.bits else None

    def report(self) -> dict:
        st = self.receiver.stats
        start = st.first_event_us or 0
        duration_s = max(1e-9, ((st.last_event_us or 0) - start) / 1e6)
        delivered = sum(len(m.message.data) for m in self.messages)
        cpu = dict(st.cpu_s)
        cpu_total = sum(cpu.values())
        config = self.receiver.config
        return {
            "link": {  # what the receiver was told the screen sends
                "profile": config.profile,
                "cells": config.cells,
                "refresh_hz": config.refresh_hz,
                "marker_size_m": config.marker_size_m,
            },
            "events": st.events,
            "duration_s": duration_s,
            "locked": bool(st.lock_times_us),
            "time_to_lock_s": (st.lock_times_us[0] - start) / 1e6 if st.lock_times_us else None,
            "tracking_losses": st.losses,
            "reacquisitions": max(0, len(st.lock_times_us) - 1),
            "detection_failures": dict(
                sorted(st.detection_failures.items(), key=lambda kv: -kv[1])
            ),
            "frames_read": st.frames_read,
            "frames_seen": st.frames_seen,
            "ber": self.ber,
            "bits_scored": self.bits,
            "pose_updates": st.pose_updates,
            "poses": len(self.poses),
            "poses_verified": sum(self.pose_verified),
            "messages": [self._message(m, start) for m in self.messages],
            "goodput_bps": delivered * 8 / duration_s,
            "stream_progress": {str(k): v for k, v in self.receiver.stream.progress().items()},
            "cpu_s": cpu,
            "realtime_factor": duration_s / cpu_total if cpu_total else None,
        }

    def _message(self, m: MessageOutput, start_us: int) -> dict:
        """A delivered message: ``verified`` only if its bytes hash to the sha256 its sender sent
        (``check`` says which check ran: none for ``paper``); with the truth, ``matches_sent``
        compares it with the bytes really sent."""
        message = m.message
        entry = {
            "name": message.name,
            "size": len(message.data),
            "sha256": message.sha256,
            "verified": message.verified,
            "check": "unchecked" if message.sender_sha256 is None else "sender's sha256",
            "t_s": (m.t_us - start_us) / 1e6,
        }
        if self.truth is not None:
            entry["matches_sent"] = message.data == self.truth.encoder.message
        return entry

    def write(self, out_dir: Path) -> dict:
        """trajectory.tum (the verified poses), trajectory_all.tum (the tentative ones too),
        messages/<name>, report.json; returns the report."""
        out_dir.mkdir(parents=True, exist_ok=True)
        t_us = np.array(self.pose_t, np.int64)
        poses = np.array(self.poses).reshape(-1, 4, 4)
        verified = np.array(self.pose_verified, bool)
        write_tum(out_dir / "trajectory.tum", t_us[verified], poses[verified])
        write_tum(out_dir / "trajectory_all.tum", t_us, poses)
        msg_dir = out_dir / "messages"
        for m in self.messages:
            msg_dir.mkdir(exist_ok=True)
            name = Path(m.message.name).name or m.message.sha256[:16]
            (msg_dir / name).write_bytes(m.message.data)
        report = self.report()
        (out_dir / "report.json").write_text(json.dumps(report, indent=2) + "\n")
        return report


def pushes(
    receiver: Receiver, chunks: Iterable[np.ndarray]
) -> Iterator[tuple[np.ndarray | None, list[Output]]]:
    """``(chunk, outputs)`` for each chunk of a time-sorted stream pushed through ``receiver``,
    then ``(None, outputs)`` of its finish: the decode loop, for callers that time each push or
    look at each one's outputs as they come."""
    for chunk in chunks:
        yield chunk, receiver.push(chunk)
    yield None, receiver.finish()


def decode_events(
    receiver: Receiver, chunks: Iterable[np.ndarray], truth: FrameTruth | None = None
) -> DecodeLog:
    """Decode a whole stream: every chunk pushed through ``receiver``, its finish, and what
    came out, collected (and scored against ``truth`` if given)."""
    log = DecodeLog(receiver, truth)
    for _, outputs in pushes(receiver, chunks):
        log.add(outputs)
    return log
