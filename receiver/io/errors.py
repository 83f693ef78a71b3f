"""Errors raised by the event readers and writers."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


class EventFileError(ValueError):
    """An event file that is truncated, corrupt or not in the format it claims to be.

    The message names the file and where the problem is (a byte offset, or an event index for
    formats without a byte layout, such as HDF5 datasets).
    """

    def __init__(
        self, path: str | Path, problem: str, *, offset: int | None = None, where: str | None = None
    ) -> None:
        self.path = Path(path)
        self.offset = offset
        self.problem = problem
        if where is None:
            where = f"at byte {offset}" if offset is not None else "in the file"
        super().__init__(f"{self.path} {where}: {problem}")


class MissingExtraError(ImportError):
    """A format whose reader lives in an optional extra that is not installed."""

    def __init__(self, what: str, package: str, extra: str) -> None:
        super().__init__(f"{what} needs the '{package}' package: pip install 'eventocc[{extra}]'")


@contextmanager
def foreign_errors(
    path: str | Path, what: str, *, offset: int | None = None, where: str | None = None
) -> Iterator[None]:
    """Raise what a third-party decoder raises inside as ``EventFileError(path, what (...))``.

    For a damaged file h5py, rosbags, apsw, aedat and numpy's npy parser raise unrelated types
    (KeyError, RuntimeError, TypeError, apsw.CorruptError, tokenize.TokenError, ...), and a
    Rust decoder's panic arrives as pyo3's ``PanicException``, which derives from
    ``BaseException`` so that ``except Exception`` lets it pass. Interrupts and exits pass.
    """
    try:
        yield
    except EventFileError:
        raise
    except BaseException as error:
        if not isinstance(error, Exception) and type(error).__name__ != "PanicException":
            raise
        raise EventFileError(
            path, f"{what} ({type(error).__name__}: {error})", offset=offset, where=where
        ) from None
