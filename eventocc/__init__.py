"""eventocc: a screen-to-event-camera data link with 6-DoF pose.

One import root over the repository's folders: ``eventocc.occ`` (the link format, ``occ/``),
``eventocc.server`` (``server/``), ``eventocc.receiver`` (``receiver/``) and the static pages,
``eventocc.web`` (``web/``).
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("eventocc")
except PackageNotFoundError:  # a checkout on sys.path without an install
    __version__ = "0+unknown"
