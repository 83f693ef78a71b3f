"""Camera calibration files: load and save ``CameraModel`` in three common layouts.

- ``ros``: ROS ``camera_info`` YAML (camera_calibration's output): ``image_width``,
  ``image_height``, ``camera_matrix.data`` (9 numbers, row-major), ``distortion_model:
  plumb_bob``, ``distortion_coefficients.data`` (k1 k2 p1 p2 k3).
- ``opencv``: OpenCV ``FileStorage`` YAML (``%YAML:1.0``) or JSON with ``camera_matrix`` and
  ``distortion_coefficients`` matrices and ``image_width``/``image_height``.
- ``eventocc``: a ``camera:`` block, as in the paper authors' parameter file::

      camera:
        width: 1280
        height: 720
        fx: 1033.689
        fy: 1037.050
        cx: 624.771
        cy: 321.822
        distortion_model: plumb_bob
        distortion_coeffs: [-0.032681, 0.066110, 0.001529, 0.000190, 0.0]
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

from eventocc.receiver.camera import CameraModel

CALIBRATION_FORMATS = ("ros", "opencv", "eventocc")
# The distortion model CameraModel implements, under the names tools use for it.
PLUMB_BOB = ("plumb_bob", "radtan", "rational_polynomial")


class CalibrationError(ValueError):
    """A calibration file with a missing or wrong field; the message names the field."""

    def __init__(self, path: str | Path, problem: str) -> None:
        self.path = Path(path)
        super().__init__(f"{self.path}: {problem}")


def load_calibration(path: str | Path) -> CameraModel:
    """Read a camera model from any of the layouts in ``CALIBRATION_FORMATS``."""
    path = Path(path)
    text = path.read_text()
    if text.startswith("%YAML:") or "opencv-matrix" in text:
        return _load_opencv(path)
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise CalibrationError(path, f"not YAML or JSON ({e})") from None
    if not isinstance(doc, dict):
        raise CalibrationError(path, "expected a mapping of calibration fields")
    if "camera" in doc:
        return _from_camera_block(path, doc["camera"])
    return _from_ros(path, doc)


def save_calibration(camera: CameraModel, path: str | Path, *, format: str | None = None) -> None:
    """Write ``camera``; the layout is ``format`` or, by extension, opencv for ``.json`` and
    ros otherwise."""
    path = Path(path)
    format = format or ("opencv" if path.suffix.lower() == ".json" else "ros")
    if format == "opencv":
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
        fs.write("image_width", camera.width)
        fs.write("image_height", camera.height)
        fs.write("camera_matrix", camera.K)
        fs.write("distortion_coefficients", camera.dist.reshape(1, -1))
        fs.release()
        return
    if format == "ros":
        doc: dict[str, Any] = {
            "image_width": camera.width,
            "image_height": camera.height,
            "camera_matrix": {"rows": 3, "cols": 3, "data": camera.K.ravel().tolist()},
            "distortion_model": "plumb_bob",
            "distortion_coefficients": {
                "rows": 1,
                "cols": camera.dist.size,
                "data": camera.dist.tolist(),
            },
        }
    elif format == "eventocc":
        doc = {
            "camera": {
                "width": camera.width,
                "height": camera.height,
                "fx": float(camera.K[0, 0]),
                "fy": float(camera.K[1, 1]),
                "cx": float(camera.K[0, 2]),
                "cy": float(camera.K[1, 2]),
                "distortion_model": "plumb_bob",
                "distortion_coeffs": camera.dist.tolist(),
            }
        }
    else:
        raise ValueError(
            f"unknown calibration format {format!r}; choose one of {CALIBRATION_FORMATS}"
        )
    path.write_text(yaml.safe_dump(doc, sort_keys=False))


def _field(path: Path, doc: Any, key: str, where: str = "") -> Any:
    if not isinstance(doc, dict) or key not in doc or doc[key] is None:
        raise CalibrationError(path, f"missing field '{where}{key}'")
    return doc[key]


def _numbers(path: Path, value: Any, name: str, sizes: tuple[int, ...]) -> np.ndarray:
    try:
        array = np.asarray(value, dtype=np.float64).ravel()
    except (TypeError, ValueError):
        raise CalibrationError(path, f"field '{name}' must be a list of numbers") from None
    if array.size not in sizes or not np.all(np.isfinite(array)):
        raise CalibrationError(
            path,
            f"field '{name}' must hold {' or '.join(map(str, sizes))} "
            f"finite numbers, got {array.size}",
        )
    return array


def _size(path: Path, value: Any, name: str) -> int:
    if (
        isinstance(value, bool)
        or not isinstance(value, int | float)
        or value <= 0
        or value != int(value)
    ):
        raise CalibrationError(path, f"field '{name}' must be a positive integer, got {value!r}")
    return int(value)


def _check_model(path: Path, model: Any, name: str) -> None:
    if str(model).lower() not in PLUMB_BOB:
        raise CalibrationError(
            path, f"field '{name}' is {model!r}; only plumb_bob (radtan) distortion is supported"
        )


def _model(path: Path, width: int, height: int, K: np.ndarray, dist: np.ndarray) -> CameraModel:
    try:
        return CameraModel(width, height, K.reshape(3, 3), dist)
    except ValueError as e:
        raise CalibrationError(path, str(e)) from None


def _from_ros(path: Path, doc: dict) -> CameraModel:
    width = _size(path, _field(path, doc, "image_width"), "image_width")
    height = _size(path, _field(path, doc, "image_height"), "image_height")
    K = _numbers(
        path,
        _field(path, _field(path, doc, "camera_matrix"), "data", "camera_matrix."),
        "camera_matrix.data",
        (9,),
    )
    _check_model(path, doc.get("distortion_model", "plumb_bob"), "distortion_model")
    dist_block = _field(path, doc, "distortion_coefficients")
    dist = _numbers(
        path,
        _field(path, dist_block, "data", "distortion_coefficients."),
        "distortion_coefficients.data",
        (4, 5, 8),
    )
    return _model(path, width, height, K, dist)


def _from_camera_block(path: Path, block: Any) -> CameraModel:
    def get(key: str) -> Any:
        return _field(path, block, key, "camera.")

    width = _size(path, get("width"), "camera.width")
    height = _size(path, get("height"), "camera.height")
    fx, fy, cx, cy = (
        _numbers(path, get(k), f"camera.{k}", (1,))[0] for k in ("fx", "fy", "cx", "cy")
    )
    _check_model(path, block.get("distortion_model", "plumb_bob"), "camera.distortion_model")
    dist = _numbers(
        path, block.get("distortion_coeffs", [0.0] * 5), "camera.distortion_coeffs", (4, 5, 8)
    )
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    return _model(path, width, height, K, dist)


def _load_opencv(path: Path) -> CameraModel:
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    try:
        if not fs.isOpened():
            raise CalibrationError(path, "OpenCV FileStorage cannot open this file")

        def node(name: str):
            n = fs.getNode(name)
            if n.empty():
                raise CalibrationError(path, f"missing field '{name}'")
            return n

        width = _size(path, node("image_width").real(), "image_width")
        height = _size(path, node("image_height").real(), "image_height")
        K = node("camera_matrix").mat()
        dist = node("distortion_coefficients").mat()
        if K is None or dist is None:
            raise CalibrationError(
                path,
                "fields 'camera_matrix' and 'distortion_coefficients' must be opencv-matrix nodes",
            )
        K = _numbers(path, K, "camera_matrix", (9,))
        dist = _numbers(path, dist, "distortion_coefficients", (4, 5, 8))
    finally:
        fs.release()
    return _model(path, width, height, K, dist)
