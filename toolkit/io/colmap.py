"""COLMAP sparse models, text and binary, read and written exactly (float64 round-trip).

Hand-written with numpy rather than through pycolmap: pycolmap 4 wraps every image in rigs and
frames and rewrites files it did not create, while the format itself is small and stable. Tests
cross-check our files against pycolmap's reader.
"""

from __future__ import annotations

import struct
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from toolkit.errors import SceneError
from toolkit.types import Camera, SparseModel

# COLMAP camera model id → (name, number of params)
CAMERA_MODELS = {
    0: ("SIMPLE_PINHOLE", 3), 1: ("PINHOLE", 4), 2: ("SIMPLE_RADIAL", 4), 3: ("RADIAL", 5),
    4: ("OPENCV", 8), 5: ("OPENCV_FISHEYE", 8), 6: ("FULL_OPENCV", 12), 7: ("FOV", 5),
    8: ("SIMPLE_RADIAL_FISHEYE", 4), 9: ("RADIAL_FISHEYE", 5), 10: ("THIN_PRISM_FISHEYE", 12),
}
MODEL_IDS = {name: (mid, n) for mid, (name, n) in CAMERA_MODELS.items()}


# --- rotations --------------------------------------------------------------------------------
def qvec_to_rotmat(q: np.ndarray) -> np.ndarray:
    """(...,4) w,x,y,z → (...,3,3)."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def rotmat_to_qvec(R: np.ndarray) -> np.ndarray:
    """(...,3,3) → (...,4) w,x,y,z with w ≥ 0 (via scipy)."""
    from scipy.spatial.transform import Rotation

    R = np.asarray(R, dtype=np.float64)
    xyzw = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_quat()
    q = np.concatenate([xyzw[:, 3:], xyzw[:, :3]], axis=1)
    q[q[:, 0] < 0] *= -1
    return q.reshape(R.shape[:-2] + (4,))


# --- reading ----------------------------------------------------------------------------------
def read_model(path: str | Path) -> SparseModel:
    """Read a model folder holding cameras/images/points3D as .bin or .txt."""
    path = Path(path)
    if not path.is_dir():
        raise SceneError(f"{path}: COLMAP model folder not found")
    if (path / "cameras.bin").is_file():
        ext, reader = ".bin", (_read_cameras_bin, _read_images_bin, _read_points_bin)
    elif (path / "cameras.txt").is_file():
        ext, reader = ".txt", (_read_cameras_txt, _read_images_txt, _read_points_txt)
    else:
        raise SceneError(f"{path}: no cameras.txt or cameras.bin in the COLMAP model folder")
    files = [path / f"{n}{ext}" for n in ("cameras", "images", "points3D")]
    for f in files:
        if not f.is_file():
            raise SceneError(f"{f}: file not found")
    try:
        cameras = reader[0](files[0])
        images = reader[1](files[1])
        points = reader[2](files[2])
    except SceneError:
        raise
    except Exception as exc:
        raise SceneError(f"{path}: corrupt COLMAP model ({type(exc).__name__}: {exc})") from exc
    return _assemble(path, cameras, images, points)


def _assemble(path, cameras, images, points) -> SparseModel:
    ids, cam_ids, names, qs, ts, obs = [], [], [], [], [], []
    pid, pxyz, prgb, perr = points
    index_of_point = {int(p): i for i, p in enumerate(pid)}
    for k, (iid, q, t, cid, name, xys, p3d) in enumerate(images):
        if cid not in cameras:
            raise SceneError(f"{path}: image {name!r} references missing camera {cid}")
        ids.append(iid), cam_ids.append(cid), names.append(name), qs.append(q), ts.append(t)
        valid = p3d >= 0
        if valid.any():
            idx = np.array([index_of_point.get(int(p), -1) for p in p3d[valid]])
            if (idx < 0).any():
                missing = int(p3d[valid][idx < 0][0])
                raise SceneError(f"{path}: image {name!r} references missing 3D point {missing}")
            obs.append(np.column_stack([np.full(len(idx), k), idx, xys[valid]]))
    observations = np.concatenate(obs) if obs else np.zeros((0, 4))
    return SparseModel(
        cameras=cameras, image_names=tuple(names), image_ids=np.array(ids, dtype=np.int64),
        camera_ids=np.array(cam_ids, dtype=np.int64),
        R=qvec_to_rotmat(np.array(qs).reshape(-1, 4)) if qs else np.zeros((0, 3, 3)),
        t=np.array(ts, dtype=np.float64).reshape(-1, 3),
        points3d_ids=np.asarray(pid, dtype=np.int64), points3d=np.asarray(pxyz, np.float64).reshape(-1, 3),
        points3d_rgb=np.asarray(prgb, np.uint8).reshape(-1, 3), observations=observations,
        qvec=np.array(qs, dtype=np.float64).reshape(-1, 4),
        points3d_error_px=np.asarray(perr, np.float64).reshape(-1),
    )


def _qvecs(model: SparseModel) -> np.ndarray:
    """Quaternions to write: the ones read from file while R still equals them, else from R."""
    if model.qvec is not None and len(model.qvec) == len(model.R) and \
            np.array_equal(qvec_to_rotmat(model.qvec), model.R):
        return model.qvec
    return rotmat_to_qvec(model.R) if len(model.R) else np.zeros((0, 4))


def _data_lines(path: Path):
    with open(path) as fh:
        return [ln.rstrip("\n") for ln in fh if ln.strip() and not ln.startswith("#")]


def _read_cameras_txt(path: Path) -> dict[int, Camera]:
    cams = {}
    for ln in _data_lines(path):
        w = ln.split()
        if w[1] not in MODEL_IDS or len(w) - 4 != MODEL_IDS[w[1]][1]:
            raise SceneError(f"{path}: bad camera line {ln[:60]!r}")
        cams[int(w[0])] = Camera(int(w[0]), w[1], int(w[2]), int(w[3]), np.array(w[4:], dtype=np.float64))
    return cams


def _read_images_txt(path: Path):
    # Blank lines are meaningful here (an image with no observations), so only comments are dropped.
    with open(path) as fh:
        lines = [ln for ln in fh.read().split("\n") if not ln.startswith("#")]
    if lines and lines[-1] == "":
        lines.pop()  # the artefact of the final newline
    if len(lines) % 2 and not lines[-1].strip():
        lines.pop()  # one extra blank line at the end is tolerated
    if len(lines) % 2:
        raise SceneError(f"{path}: images.txt has an odd number of lines ({len(lines)}); "
                         "each image needs a pose line and an observation line")
    images = []
    for a, b in zip(lines[0::2], lines[1::2]):
        w = a.split()
        if len(w) < 10:
            raise SceneError(f"{path}: bad image line {a[:60]!r}")
        obs = np.array(b.split(), dtype=np.float64).reshape(-1, 3) if b.strip() else np.zeros((0, 3))
        images.append((int(w[0]), np.array(w[1:5], float), np.array(w[5:8], float), int(w[8]),
                       " ".join(w[9:]), obs[:, :2], obs[:, 2].astype(np.int64)))
    return images


def _read_points_txt(path: Path):
    lines = _data_lines(path)
    ids = np.array([int(ln.split(maxsplit=1)[0]) for ln in lines], dtype=np.int64)
    xyz = np.array([ln.split()[1:4] for ln in lines], dtype=np.float64).reshape(-1, 3)
    rgb = np.array([ln.split()[4:7] for ln in lines], dtype=np.int64).reshape(-1, 3)
    error = np.array([ln.split()[7] for ln in lines], dtype=np.float64)
    return ids, xyz, rgb, error


def _read_cameras_bin(path: Path) -> dict[int, Camera]:
    buf = path.read_bytes()
    (n,), off, cams = struct.unpack_from("<Q", buf), 8, {}
    for _ in range(n):
        cid, mid, w, h = struct.unpack_from("<iiQQ", buf, off)
        off += 24
        name, k = CAMERA_MODELS[mid]
        params = np.frombuffer(buf, "<f8", k, off).astype(np.float64)
        off += 8 * k
        cams[cid] = Camera(cid, name, int(w), int(h), params)
    return cams


def _read_images_bin(path: Path):
    buf = path.read_bytes()
    (n,), off, images = struct.unpack_from("<Q", buf), 8, []
    for _ in range(n):
        iid = struct.unpack_from("<i", buf, off)[0]
        qt = np.frombuffer(buf, "<f8", 7, off + 4)
        cid = struct.unpack_from("<i", buf, off + 60)[0]
        end = buf.index(b"\x00", off + 64)
        name = buf[off + 64:end].decode()
        off = end + 1
        (k,) = struct.unpack_from("<Q", buf, off)
        off += 8
        rec = np.frombuffer(buf, np.dtype([("x", "<f8"), ("y", "<f8"), ("id", "<i8")]), k, off)
        off += 24 * k
        images.append((iid, qt[:4].copy(), qt[4:].copy(), cid, name,
                       np.column_stack([rec["x"], rec["y"]]), rec["id"].astype(np.int64)))
    return images


def _read_points_bin(path: Path):
    buf = path.read_bytes()
    (n,), off = struct.unpack_from("<Q", buf), 8
    ids, xyz, rgb = np.empty(n, np.int64), np.empty((n, 3)), np.empty((n, 3), np.uint8)
    error = np.empty(n)
    for i in range(n):
        ids[i] = struct.unpack_from("<Q", buf, off)[0]
        xyz[i] = np.frombuffer(buf, "<f8", 3, off + 8)
        rgb[i] = np.frombuffer(buf, "u1", 3, off + 32)
        (error[i], k) = struct.unpack_from("<dQ", buf, off + 35)
        off += 51 + 8 * k
    return ids, xyz, rgb, error


# --- writing ----------------------------------------------------------------------------------
class _Tracks:
    """Observations grouped both ways, as flat arrays (no per-observation Python objects).

    By image (COLMAP's POINTS2D order: file order of the observations within each image):
    ``uv``/``pid`` rows, image k's rows are ``img_start[k]:img_start[k+1]``. By point (TRACK order:
    image file order, then 2D index): ``track`` rows (image_id, point2d_idx), point i's rows are
    ``pt_start[i]:pt_start[i+1]``.
    """

    def __init__(self, model: SparseModel) -> None:
        obs = np.asarray(model.observations, dtype=np.float64).reshape(-1, 4)
        img = obs[:, 0].astype(np.int64)
        pt = obs[:, 1].astype(np.int64)
        by_img = np.argsort(img, kind="stable")
        n_img, n_pt = len(model.image_names), len(model.points3d_ids)
        self.img_start = np.searchsorted(img[by_img], np.arange(n_img + 1))
        self.uv = obs[by_img, 2:4]
        self.pid = np.asarray(model.points3d_ids, np.int64)[pt[by_img]]
        point2d_idx = np.arange(len(by_img)) - self.img_start[img[by_img]]
        by_pt = np.argsort(pt[by_img], kind="stable")
        self.pt_start = np.searchsorted(pt[by_img][by_pt], np.arange(n_pt + 1))
        image_ids = np.asarray(model.image_ids, np.int64)
        self.track = np.stack([image_ids[img[by_img][by_pt]], point2d_idx[by_pt]], axis=1)


def write_model(model: SparseModel, path: str | Path, binary: bool = False) -> None:
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    (_write_bin if binary else _write_txt)(model, path)


def _interleave(n: int, *columns: Iterable[str]) -> list[str]:
    """Row-major tokens of ``n`` rows given column by column (rows are then slices of the list)."""
    out = [""] * (n * len(columns))
    for k, col in enumerate(columns):
        out[k::len(columns)] = col
    return out


def _write_txt(model: SparseModel, path: Path) -> None:
    # Floats are written with repr (shortest exact round-trip). Tokens are made column by column from
    # flat lists: map(repr, …) is the C-level floor, and 2-D .tolist() would create one list per row
    # (garbage-collector work that cost as much as the formatting).
    tr = _Tracks(model)
    with open(path / "cameras.txt", "w") as fh:
        fh.write("# CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n")
        for cid in sorted(model.cameras):
            c = model.cameras[cid]
            fh.write(" ".join([str(cid), c.model, str(c.width), str(c.height), *map(repr, map(float, c.params))]) + "\n")
    qs = _qvecs(model)
    uv = _interleave(len(tr.pid), map(repr, tr.uv[:, 0].tolist()), map(repr, tr.uv[:, 1].tolist()),
                     map(str, tr.pid.tolist()))
    img_start = (3 * tr.img_start).tolist()
    with open(path / "images.txt", "w") as fh:
        fh.write("# IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n# POINTS2D[] as (X, Y, POINT3D_ID)\n")
        for k, name in enumerate(model.image_names):
            vals = [*map(float, qs[k]), *map(float, model.t[k])]
            fh.write(" ".join([str(int(model.image_ids[k])), *map(repr, vals), str(int(model.camera_ids[k])), name]) + "\n")
            fh.write(" ".join(uv[img_start[k]:img_start[k + 1]]) + "\n")
    xyz, rgb = np.asarray(model.points3d, np.float64).reshape(-1, 3), np.asarray(model.points3d_rgb).reshape(-1, 3)
    n_pt = len(xyz)
    head = _interleave(n_pt, map(str, np.asarray(model.points3d_ids).tolist()),
                       *(map(repr, xyz[:, d].tolist()) for d in range(3)),
                       *(map(str, rgb[:, d].tolist()) for d in range(3)), map(repr, _errors(model).tolist()))
    track = list(map(str, tr.track.ravel().tolist()))
    starts = (2 * tr.pt_start).tolist()
    with open(path / "points3D.txt", "w") as fh:
        fh.write("# POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n")
        fh.writelines(f"{' '.join(head[8 * i:8 * i + 8])} {' '.join(track[starts[i]:starts[i + 1]])}\n"
                      for i in range(n_pt))


def _errors(model: SparseModel) -> np.ndarray:
    """(P,) the ERROR column: each point's mean reprojection error (px), 0 when unknown."""
    n = len(model.points3d_ids)
    if model.points3d_error_px is None or len(model.points3d_error_px) != n:
        return np.zeros(n)
    return np.asarray(model.points3d_error_px, np.float64)


_POINT2D = np.dtype([("x", "<f8"), ("y", "<f8"), ("id", "<i8")])
_POINT_HEAD = np.dtype([("id", "<u8"), ("xyz", "<f8", 3), ("rgb", "u1", 3), ("error", "<f8"), ("n", "<u8")])


def _write_bin(model: SparseModel, path: Path) -> None:
    tr = _Tracks(model)
    with open(path / "cameras.bin", "wb") as fh:
        fh.write(struct.pack("<Q", len(model.cameras)))
        for cid in sorted(model.cameras):
            c = model.cameras[cid]
            fh.write(struct.pack("<iiQQ", cid, MODEL_IDS[c.model][0], c.width, c.height))
            fh.write(np.asarray(c.params, "<f8").tobytes())
    qs = _qvecs(model)
    rec = np.empty(len(tr.pid), _POINT2D)
    rec["x"], rec["y"], rec["id"] = tr.uv[:, 0], tr.uv[:, 1], tr.pid
    with open(path / "images.bin", "wb") as fh:
        fh.write(struct.pack("<Q", len(model.image_names)))
        for k, name in enumerate(model.image_names):
            fh.write(struct.pack("<i", int(model.image_ids[k])))
            fh.write(np.concatenate([qs[k], model.t[k]]).astype("<f8").tobytes())
            fh.write(struct.pack("<i", int(model.camera_ids[k])) + name.encode() + b"\x00")
            fh.write(struct.pack("<Q", tr.img_start[k + 1] - tr.img_start[k]))
            fh.write(rec[tr.img_start[k]:tr.img_start[k + 1]].tobytes())
    head = np.zeros(len(model.points3d_ids), _POINT_HEAD)
    head["id"], head["xyz"], head["rgb"] = model.points3d_ids, model.points3d, model.points3d_rgb
    head["error"] = _errors(model)
    head["n"] = np.diff(tr.pt_start)
    head_bytes, track_bytes = head.tobytes(), tr.track.astype("<i4").tobytes()
    hs, ts = _POINT_HEAD.itemsize, 8  # one track element: two int32
    starts = tr.pt_start.tolist()
    with open(path / "points3D.bin", "wb") as fh:
        fh.write(struct.pack("<Q", len(model.points3d_ids)))
        fh.write(b"".join(head_bytes[i * hs:(i + 1) * hs] + track_bytes[starts[i] * ts:starts[i + 1] * ts]
                          for i in range(len(head))))


def replace_poses(model: SparseModel, R: np.ndarray, t: np.ndarray, points3d: np.ndarray | None = None,
                  points3d_error_px: np.ndarray | None = None) -> SparseModel:
    """A copy of ``model`` with new world-to-camera poses (and optionally 3D points); the points'
    reprojection errors are ``points3d_error_px`` (None: unknown, the old ones no longer hold)."""
    from dataclasses import replace

    return replace(model, R=np.asarray(R, np.float64), t=np.asarray(t, np.float64), qvec=None,
                   points3d=model.points3d if points3d is None else np.asarray(points3d, np.float64),
                   points3d_error_px=points3d_error_px)
