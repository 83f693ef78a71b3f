"""The ASCII header (``% key value`` lines) that starts Prophesee RAW and DAT files."""

from __future__ import annotations

from typing import BinaryIO

# A longer "line" is binary payload that happens to start with "% ".
MAX_HEADER_LINE = 1024
# Writers put a dozen or two lines; more is payload that looks like a header, read as payload.
MAX_HEADER_LINES = 1000

# Legacy files name only the HAL plugin; its sensor generation fixes the geometry.
# (substring of plugin_name, (width, height)), most specific first.
PLUGIN_GEOMETRY: tuple[tuple[str, tuple[int, int]], ...] = (
    ("genx320", (320, 320)),
    ("gen3", (640, 480)),
    ("gen4", (1280, 720)),
    ("imx636", (1280, 720)),
    ("evk4", (1280, 720)),
    ("imx8", (640, 512)),
)


def read_header(f: BinaryIO) -> tuple[dict[str, str], int]:
    """Header keys (lower-cased) and the payload offset; ``f`` is left at the payload.

    Follows OpenEB: lines are read while the next two bytes are ``"% "``, up to and including
    ``% end`` (which some writers omit).
    """
    f.seek(0)
    header: dict[str, str] = {}
    offset = 0
    for _ in range(MAX_HEADER_LINES):
        if f.read(2) != b"% ":
            break
        f.seek(offset)
        line = f.readline(MAX_HEADER_LINE)
        if not line.endswith(b"\n") or not line.isascii():
            break
        key, _, value = line[2:].decode("ascii").strip().partition(" ")
        offset += len(line)
        if key == "end":
            break
        header[key.lower()] = value.strip()
    f.seek(offset)
    return header, offset


def format_fields(header: dict[str, str]) -> dict[str, str]:
    """``% format EVT3;height=720;width=1280`` as ``{"name": "EVT3", "height": "720", ...}``."""
    name, *params = header.get("format", "").split(";")
    fields = dict(p.split("=", 1) for p in params if "=" in p)
    fields["name"] = name.strip().upper()
    return fields


def header_geometry(header: dict[str, str]) -> tuple[int, int] | None:
    """Sensor (width, height) from whichever key the writer used, or ``None`` if unknown."""
    fields = format_fields(header)
    try:
        if "width" in fields and "height" in fields:
            return int(fields["width"]), int(fields["height"])
        if "geometry" in header:
            w, h = header["geometry"].lower().split("x")
            return int(w), int(h)
        if "width" in header and "height" in header:  # DAT files
            return int(header["width"]), int(header["height"])
    except ValueError:
        return None
    plugin = header.get("plugin_name", "").lower()
    for token, geometry in PLUGIN_GEOMETRY:
        if token in plugin:
            return geometry
    return None


def write_header(lines: dict[str, str], *, end: bool) -> bytes:
    return b"".join(f"% {k} {v}\n".encode("ascii") for k, v in lines.items()) + (
        b"% end\n" if end else b""
    )
