"""``street_density_factor`` K > 1: each MVS point written as K consecutive rows of ``street/cloud.laz``.

Row i*K is MVS point i of the K = 1 scene, bit for bit before LAS quantisation. Rows i*K+1 … i*K+K-1
sample the same surface again: the noise-free hit point of point i moved in the hit triangle's plane
by uniform offsets in [-point_spacing_m/2, +point_spacing_m/2] along two tangent axes, plus fresh MVS
noise of point i's sigma (``street.noise_sigma`` of its depth); same colour and capturing camera, so
the same drift (``Drift.apply``). A gross outlier's extra samples start from its noisy (outlier)
position instead of the hit, offset and noised like the others: they stay a small clump of outliers.
Extra samples come from their own random stream (``density``), so every K = 1 stream is consumed as
at K = 1. The chunk is densified and written ``BLOCK_ROWS`` output rows at a time.

The LAS frame: point format 2 (RGB, LAS 1.2), scale ``las_scale`` = the largest 1/2/5·10^n ≤
0.0005 × street_scale (≤ 0.25 mm quantisation error in metres), offset = the centre of the drifted
camera centres' box in the street frame, rounded to 100 units, known before any point is written.
"""

from __future__ import annotations

import datetime
from pathlib import Path

import numpy as np

from toolkit.errors import CrossviewError
from toolkit.synth.config import SynthConfig
from toolkit.synth.drift import Drift
from toolkit.synth.street import StreetChunk

BLOCK_ROWS = 1 << 21  # output rows densified and compressed at a time
LAS_DATE = datetime.date(2020, 1, 1)  # fixed: the same seed gives the same bytes
OFFSET_ROUND = 100.0
_INT32 = 2**31 - 1


def las_scale(street_scale: float) -> float:
    """The largest 1, 2 or 5 × 10^n at most 0.5 mm in metres, in street-frame units."""
    target = 0.0005 * street_scale
    e = np.floor(np.log10(target))
    return float(max(m * 10.0**e for m in (1, 2, 5) if m * 10.0**e <= target * (1 + 1e-12)))


def las_frame(drift: Drift, cfg: SynthConfig) -> tuple[np.ndarray, float]:
    """(offset (3,), scale) of the LAS integers, from the drifted route before any point exists.

    Every point lies within reach of a drifted camera centre: ≤ 12 max_range_m along a ray of depth
    ≤ max_range_m in a < 170° view, plus 100 m for gross outliers (~20 m along their ray) and the
    capture-to-camera step, times the drift scale. A route too long for int32 at this scale is refused
    here rather than mid-file."""
    k = drift.global_scale
    centres = k * (drift.drift_centres @ drift.global_rotation.T + drift.global_translation)
    lo, hi = centres.min(0), centres.max(0)
    offset = np.round((lo + hi) / 2 / OFFSET_ROUND) * OFFSET_ROUND + 0.0  # no -0.0
    scale = las_scale(k)
    margin = (12 * cfg.max_range_m + 100) * float(drift.drift_scale.max()) * k
    reach = float(np.max(np.maximum(hi - offset, offset - lo))) + margin
    if reach / scale > 0.9 * _INT32:
        raise CrossviewError(f"synth: street_density_factor: the street frame reaches {reach:.0f} units from the "
                             f"LAS offset, beyond int32 steps of {scale:g}; use a shorter route")
    return offset, scale


def tangent_axes(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit axes spanning the plane of each unit normal (N,3)."""
    n = normals.astype(np.float64)
    ref = np.zeros_like(n)
    steep = np.abs(n[:, 2]) > 0.9
    ref[~steep, 2] = 1.0
    ref[steep, 0] = 1.0
    t1 = np.cross(n, ref)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    return t1, np.cross(n, t1)


class DenseCloudWriter:
    """``write(chunk, street)`` per captured chunk, in route order, then ``close``."""

    def __init__(self, path: Path, drift: Drift, cfg: SynthConfig, origin3: np.ndarray, rng: np.random.Generator):
        import laspy

        self.path, self.drift, self.cfg, self.origin3, self.rng = path, drift, cfg, origin3, rng
        self.k = int(cfg.street_density_factor)
        self.offset, self.scale = las_frame(drift, cfg)
        header = laspy.LasHeader(point_format=2, version="1.2")
        header.offsets, header.scales = self.offset, np.full(3, self.scale)
        header.creation_date = LAS_DATE
        header.generating_software = "crossview synth"
        self.header = header
        self._writer = laspy.open(path, mode="w", header=header, laz_backend=laspy.LazBackend.Lazrs)
        self.rows = 0

    def write(self, ch: StreetChunk, street: np.ndarray) -> None:
        """The K rows of each point of ``ch``; ``street`` (N,3) is its K = 1 street-frame position."""
        per = max(1, BLOCK_ROWS // self.k)
        t1, t2 = tangent_axes(ch.normals)
        for a in range(0, len(street), per):
            b = min(len(street), a + per)
            self._block(ch, street, t1, t2, a, b)

    def _block(self, ch: StreetChunk, street: np.ndarray, t1: np.ndarray, t2: np.ndarray, a: int, b: int) -> None:
        import laspy

        k1, n, half = self.k - 1, b - a, self.cfg.point_spacing_m / 2
        base = np.where(ch.outlier[a:b, None], ch.points[a:b], ch.hits[a:b])
        uv = self.rng.uniform(-half, half, (n, k1, 2))
        noise = self.rng.normal(0, 1, (n, k1, 3)) * ch.sigma[a:b, None, None]
        local = base[:, None, :] + uv[:, :, :1] * t1[a:b, None, :] + uv[:, :, 1:] * t2[a:b, None, :] + noise
        del uv, noise
        extra = self.drift.apply((local + self.origin3).reshape(-1, 3), np.repeat(ch.camera[a:b], k1))
        del local
        out = np.empty((n, self.k, 3))
        out[:, 0] = street[a:b]
        out[:, 1:] = extra.reshape(n, k1, 3)
        del extra
        q = np.round((out.reshape(-1, 3) - self.offset) / self.scale)
        del out
        if np.abs(q).max() > _INT32:
            raise CrossviewError(f"{self.path}: a street point beyond the LAS int32 range (offset "
                                 f"{self.offset.tolist()}, scale {self.scale:g})")
        rec = laspy.ScaleAwarePointRecord.zeros(n * self.k, header=self.header)
        rec.array["X"], rec.array["Y"], rec.array["Z"] = q[:, 0], q[:, 1], q[:, 2]
        del q
        rgb = np.repeat(ch.colors[a:b].astype(np.uint16) * 257, self.k, axis=0)
        rec.array["red"], rec.array["green"], rec.array["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
        self._writer.write_points(rec)
        self.rows += n * self.k

    def close(self) -> None:
        self._writer.close()
