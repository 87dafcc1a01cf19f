"""The point warp of a run as one object: what a point of the input street frame needs to be moved
into the scene CRS, reloadable from the run folder (``toolkit.warp.store``) for ``crossview apply``.

A point is moved by ``toolkit.warp.blend.point_maps`` over its *carrier* (anchor) segment and that
segment's blending neighbours. The run's own street points carry the anchors the warp stage chose
(valid carrier, else the nearest valid segment, then the pass check). A point of another cloud has
no segment label: it takes the carrier of the nearest street point of the run's cloud (3D, in the
input street frame), so the run's own points get their own carriers back. After the bundle
adjustment the run's points may instead follow their capture cameras (``PointWarp.cameras``,
``toolkit.adjust.remake``): a point of another cloud then takes the capture camera of the nearest
street point of the run.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from toolkit.threads import openmp_threads, query_workers
from toolkit.warp.blend import PointMaps, point_maps
from toolkit.warp.cameras import CameraMaps
from toolkit.warp.cells import levelled_xy
from toolkit.warp.index import SegmentIndex


NEAR_M = 0.5  # radius of the first, bounded nearest-point search (metres)


@dataclass(frozen=True)
class CarrierSource:
    """The run's street points and the segment each was moved with (the carrier rule above).

    xyz_f32: (N,3) float32 points minus ``PointWarp.origin`` (the run's input street frame);
    segment: (N,) int32 carrier segment index of each.
    """

    xyz_f32: np.ndarray
    segment: np.ndarray
    camera: np.ndarray | None = None  # (N,) capture camera of each, when the points follow the cameras

    @classmethod
    def of(cls, points: np.ndarray, segment: np.ndarray, origin: np.ndarray) -> CarrierSource:
        return cls(relative_f32(points, origin), np.asarray(segment, np.int32))

    @functools.cached_property
    def tree(self):
        # pykdtree: the same nearest points and distances as scipy's cKDTree, 15–25 % sooner on
        # the chunks of a large cloud (bench/RESULTS.md); not picklable, so __getstate__ drops it
        from pykdtree.kdtree import KDTree

        return KDTree(self.xyz_f32.astype(np.float64))

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state.pop("tree", None)  # rebuilt where it is used (a Dask worker)
        return state

    def carriers(self, points: np.ndarray, origin: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(carrier segment (n,) int64, distance to that street point (n,) metres)."""
        dist, nn = self.nearest(points, origin)
        return self.segment[nn].astype(np.int64), dist

    def cameras(self, points: np.ndarray, origin: np.ndarray) -> np.ndarray:
        """(n,) capture camera of the nearest street point (``camera`` must be set)."""
        return self.camera[self.nearest(points, origin)[1]].astype(np.int64)

    def nearest(self, points: np.ndarray, origin: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        q = relative_f32(points, origin).astype(np.float64)
        # a bounded search first (most points have a street point within centimetres; −1/3 of the
        # time on 151 M points), the exact nearest all the same; the rest searched without bound
        with openmp_threads(query_workers(len(q))):
            dist, nn = self.tree.query(q, distance_upper_bound=NEAR_M)
            far = np.flatnonzero(~np.isfinite(dist))
            if len(far):
                dist[far], nn[far] = self.tree.query(q[far])
        return dist, nn.astype(np.int64)


def relative_f32(points: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """Points relative to the local origin as float32 (stored, and queried the same way: a point of
    the run's cloud finds itself at distance 0)."""
    return (np.asarray(points, np.float64) - origin).astype(np.float32)


@dataclass(frozen=True)
class PointWarp:
    """A run's point warp, input street frame → scene CRS.

    origin (3,), up_rotation (3,3): the levelling of ``StreetSegments`` (blend distances are
    horizontal, in the levelled frame); T: (S,4,4) segment transforms; index: footprints of the
    valid segments and their blending neighbours; neighbours_k, min_distance_m, weight_cell_m,
    relative_distance: the blend's parameters (``warp.inverse_log``; ``warp.nearest`` is k = 0);
    source: the run's points and their carriers (None until the stage attaches them).
    """

    origin: np.ndarray
    up_rotation: np.ndarray
    T: np.ndarray
    index: SegmentIndex
    neighbours_k: int
    min_distance_m: float
    weight_cell_m: float
    relative_distance: bool = False
    source: CarrierSource | None = None
    street_scale: float = 1.0
    cameras: CameraMaps | None = None  # the points follow their capture camera instead (toolkit.adjust.remake)

    def _metric(self, points: np.ndarray) -> np.ndarray:
        return points if self.street_scale == 1.0 else np.asarray(points, np.float64) / self.street_scale

    def levelled_xy(self, points: np.ndarray) -> np.ndarray:
        return levelled_xy(self, self._metric(points))

    def maps(self, points: np.ndarray, carriers: np.ndarray, xy: np.ndarray | None = None,
             cameras: np.ndarray | None = None) -> PointMaps:
        """Each point's map, for points as given: the blend (``toolkit.warp.blend.point_maps``) over
        its carrier, or, when the warp follows the cameras, its capture camera's pose change
        (``cameras``; None: that of the nearest street point of the run)."""
        from dataclasses import replace

        if self.cameras is not None:
            if cameras is None:
                cameras = self.source.cameras(self._metric(points), self.origin)
            maps = self.cameras.at(cameras)
        else:
            xy = self.levelled_xy(points) if xy is None else xy
            maps = point_maps(xy, carriers, self.T, self.index, self.neighbours_k, self.min_distance_m,
                              self.weight_cell_m, self.relative_distance)
        return maps if self.street_scale == 1.0 else replace(maps, A=maps.A / self.street_scale)

    def carriers(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(carrier (n,), distance to the run's street point it was taken from (n,) m)."""
        if self.source is None:
            raise ValueError("this warp has no carrier source (the run's street points)")
        return self.source.carriers(self._metric(points), self.origin)

    def move(self, points: np.ndarray) -> tuple[PointMaps, np.ndarray, np.ndarray]:
        """Points of any cloud of the street frame: (their maps, carriers (n,), distance (n,) m to the
        run's street point both carrier and capture camera come from; one nearest-point search)."""
        if self.source is None:
            raise ValueError("this warp has no carrier source (the run's street points)")
        dist, nn = self.source.nearest(self._metric(points), self.origin)
        carriers = self.source.segment[nn].astype(np.int64)
        cameras = self.source.camera[nn].astype(np.int64) if self.cameras is not None else None
        return self.maps(points, carriers, cameras=cameras), carriers, dist

    def for_input_frame(self, street_scale: float) -> PointWarp:
        """This warp taking points in the street frame's own units."""
        from dataclasses import replace

        return replace(self, street_scale=float(street_scale))

    def following(self, cameras: CameraMaps, capture_camera: np.ndarray) -> PointWarp:
        """This warp with the run's points following their capture cameras' pose changes."""
        from dataclasses import replace

        return replace(self, cameras=cameras,
                       source=replace(self.source, camera=np.asarray(capture_camera, np.int32)))

    def with_source(self, points: np.ndarray, carriers: np.ndarray) -> PointWarp:
        from dataclasses import replace

        return replace(self, source=CarrierSource.of(points, carriers, self.origin))
