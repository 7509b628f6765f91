"""One taught vision map per route in one msgpack file: {"format", "version", "camera", "meta",
"keyframes"}; arrays as {"dtype", "shape", "data"} (little-endian bytes). Written atomically
(common/atomic_file.py): a crash leaves the old map or the new one, never half of one. Loading checks
everything and raises MapFileError with the reason."""
from __future__ import annotations

import os
from pathlib import Path

import msgpack
import numpy as np

from common.atomic_file import write_atomically
from services.localizer.vision.camera import StereoCamera
from services.localizer.vision.teach_repeat import Keyframe, VisionMap

FORMAT = "lbc.vision_map"
VERSION = 1
_CAMERA_FIELDS = ("fu", "fv", "cu", "cv", "baseline_m", "width", "height", "doffs_px")
_ARRAYS = {"points": ("<f8", 3), "desc": ("|u1", 32), "uvd": ("<f8", 3), "cov_uvd": ("<f8", 3)}


class MapFileError(ValueError):
    """The file is not a readable vision map; the message says which file and why."""


def _pack_array(a: np.ndarray, dtype: str) -> dict:
    a = np.ascontiguousarray(a, dtype=np.dtype(dtype))
    return {"dtype": dtype, "shape": list(a.shape), "data": a.tobytes()}


def save_map(path: str | os.PathLike, vmap: VisionMap) -> None:
    path = Path(path)
    for kf in vmap.keyframes:           # refuse to write what load_map would refuse to read
        arrays = [kf.points, kf.uvd, kf.T_prev_this] + ([] if kf.cov_uvd is None else [kf.cov_uvd])
        if not all(np.all(np.isfinite(a)) for a in arrays):
            raise ValueError(f"vision map not saved: keyframe {kf.index} holds non-finite values")
    cam = vmap.camera
    doc = {
        "format": FORMAT, "version": VERSION,
        "camera": {k: (int(getattr(cam, k)) if k in ("width", "height") else float(getattr(cam, k)))
                   for k in _CAMERA_FIELDS},
        "meta": dict(vmap.meta),
        "keyframes": [{"index": kf.index, "T_prev_this": _pack_array(kf.T_prev_this, "<f8"),
                       **{name: _pack_array(getattr(kf, name), dt) for name, (dt, _) in _ARRAYS.items()
                          if getattr(kf, name) is not None}}
                      for kf in vmap.keyframes],
    }
    try:
        blob = msgpack.packb(doc, use_bin_type=True)
    except (TypeError, ValueError, OverflowError) as exc:
        raise ValueError(f"vision map not serializable (meta must hold plain values): {exc}") from exc
    write_atomically(path, blob)


def _array(where: str, obj, dtype: str, cols: int | None) -> np.ndarray:
    if not isinstance(obj, dict) or set(obj) != {"dtype", "shape", "data"}:
        raise MapFileError(f"{where}: not an encoded array")
    if obj["dtype"] != dtype:
        raise MapFileError(f"{where}: dtype {obj['dtype']!r}, expected {dtype!r}")
    shape = obj["shape"]
    if not isinstance(shape, list) or not all(isinstance(n, int) and n >= 0 for n in shape):
        raise MapFileError(f"{where}: bad shape {shape!r}")
    if cols is not None and (len(shape) != 2 or shape[1] != cols):
        raise MapFileError(f"{where}: shape {shape}, expected (N, {cols})")
    data = obj["data"]
    dt = np.dtype(dtype)
    if not isinstance(data, bytes) or len(data) != int(np.prod(shape)) * dt.itemsize:
        raise MapFileError(f"{where}: {len(data) if isinstance(data, bytes) else 'no'} data bytes for shape {shape}")
    a = np.frombuffer(data, dtype=dt).reshape(shape).astype(dt.newbyteorder("="))
    if a.dtype.kind == "f" and not np.all(np.isfinite(a)):
        raise MapFileError(f"{where}: non-finite values")
    return a


def _keyframe(i: int, obj) -> Keyframe:
    where = f"keyframe {i}"
    if not isinstance(obj, dict):
        raise MapFileError(f"{where}: not a table")
    if obj.get("index") != i:
        raise MapFileError(f"{where}: index {obj.get('index')!r}, expected {i}")
    missing = [k for k in ("T_prev_this", "points", "desc", "uvd") if k not in obj]
    if missing:
        raise MapFileError(f"{where}: missing {', '.join(missing)}")
    T = _array(f"{where}.T_prev_this", obj["T_prev_this"], "<f8", 4)
    if T.shape != (4, 4) or not np.allclose(T[3], [0, 0, 0, 1]) or \
            not np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-6) or np.linalg.det(T[:3, :3]) <= 0:
        raise MapFileError(f"{where}.T_prev_this: not a rigid transform")
    if i == 0 and not np.allclose(T, np.eye(4)):
        raise MapFileError(f"{where}.T_prev_this: the first keyframe's must be identity")
    arrs = {name: _array(f"{where}.{name}", obj[name], dt, cols) for name, (dt, cols) in _ARRAYS.items()
            if obj.get(name) is not None}
    n = {name: len(a) for name, a in arrs.items()}
    if len(set(n.values())) != 1:
        raise MapFileError(f"{where}: inconsistent keypoint counts {n}")
    if "cov_uvd" in arrs and np.any(arrs["cov_uvd"] <= 0):
        raise MapFileError(f"{where}.cov_uvd: variances must be positive")
    if np.any(arrs["points"][:, 2] <= 0):
        raise MapFileError(f"{where}.points: points behind the camera")
    return Keyframe(i, arrs["points"], arrs["desc"], arrs["uvd"], T, None, arrs.get("cov_uvd"))


def load_map(path: str | os.PathLike) -> VisionMap:
    path = Path(path)
    try:
        blob = path.read_bytes()
    except FileNotFoundError:
        raise MapFileError(f"vision map {path}: no such file") from None
    except OSError as exc:
        raise MapFileError(f"vision map {path}: cannot read: {exc}") from exc
    if not blob:
        raise MapFileError(f"vision map {path}: file is empty")
    try:
        doc = msgpack.unpackb(blob, raw=False)
    except Exception as exc:            # untrusted bytes: msgpack raises many types; all mean the same
        raise MapFileError(f"vision map {path}: truncated or corrupt ({type(exc).__name__}: {exc})") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        what = doc.get("format") if isinstance(doc, dict) else type(doc).__name__
        raise MapFileError(f"vision map {path}: not a vision map file (format {what!r}, expected {FORMAT!r})")
    if doc.get("version") != VERSION:
        raise MapFileError(f"vision map {path}: unsupported version {doc.get('version')!r} (this build reads "
                           f"version {VERSION})")
    try:
        cam = doc.get("camera")
        if not isinstance(cam, dict) or set(cam) != set(_CAMERA_FIELDS):
            raise MapFileError(f"camera: expected fields {', '.join(_CAMERA_FIELDS)}")
        if not all(isinstance(cam[k], (int, float)) and not isinstance(cam[k], bool) for k in _CAMERA_FIELDS):
            raise MapFileError("camera: non-numeric field")
        try:
            camera = StereoCamera(**{k: (int(cam[k]) if k in ("width", "height") else float(cam[k]))
                                     for k in _CAMERA_FIELDS})
        except ValueError as exc:
            raise MapFileError(f"camera: {exc}") from None
        meta = doc.get("meta")
        if not isinstance(meta, dict):
            raise MapFileError("meta: not a table")
        kfs = doc.get("keyframes")
        if not isinstance(kfs, list) or not kfs:
            raise MapFileError("no keyframes")
        return VisionMap([_keyframe(i, kf) for i, kf in enumerate(kfs)], camera, meta)
    except MapFileError as exc:
        raise MapFileError(f"vision map {path}: {exc}") from None
