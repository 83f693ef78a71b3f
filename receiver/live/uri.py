"""Sources named by URI:

- ``sim:`` the virtual event camera, watching what the server's transmitter plays right now;
  ``sim:MESSAGE_ID`` watches that message until a transmitter page reports (``sim:``: the
  newest upload);
- ``file:PATH`` (or just ``PATH``) a recording, replayed at real-time pace or as fast as possible;
- ``nd:`` / ``metavision:[SERIAL]`` / ``dv:`` a live camera through an optional backend
  (neuromorphic-drivers, Metavision's Python API, dv-processing);
- ``nd-replay:PATH`` a recording replayed as a USB camera through the neuromorphic-drivers
  path (``nd_replay``).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from eventocc.receiver.live.sources import EventSource, RecordingSource, SourceError

if TYPE_CHECKING:
    from eventocc.receiver.live.controls import CameraSettings


def open_source(
    uri: str,
    *,
    realtime: bool = True,
    live_settings: CameraSettings | None = None,
    **virtual_camera_options,
) -> EventSource:
    """The source a URI names (see the module docstring); raises ``SourceError`` if it can't.
    ``live_settings``: a live camera's ``controls.CameraSettings`` (default: its own)."""
    scheme, sep, rest = uri.partition(":")
    if not sep or len(scheme) == 1:  # a plain path (or a Windows drive letter)
        scheme, rest = "file", uri
    if scheme == "file":
        return RecordingSource(Path(rest), realtime=realtime)
    if scheme == "sim":
        from eventocc.receiver.live.virtual_camera import VirtualCamera

        return VirtualCamera(stand_in=rest or None, **virtual_camera_options)
    from eventocc.receiver.live.cameras import LIVE_BACKENDS, open_live_camera

    if scheme in LIVE_BACKENDS:
        return open_live_camera(scheme, rest, live_settings)
    raise SourceError(
        f"unknown source {uri!r}: use sim:, file:PATH, or a live camera "
        f"({', '.join(f'{name}:' for name in LIVE_BACKENDS)})"
    )
