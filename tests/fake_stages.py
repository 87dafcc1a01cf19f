"""Tiny fake stages for runner/recipe tests (registered in a private Registry)."""

from __future__ import annotations

import numpy as np
from pydantic import Field

from toolkit.errors import StageError
from toolkit.observe import DebugImage, DebugScalar
from toolkit.registry import Registry
from toolkit.scene import load_raster
from toolkit.stage import Stage, StageParams
from toolkit.types import (
    OverviewSegments, Registration, SegmentTransforms, StreetSegments, Matches, ConjugateGraphs,
    DataCosts,
)


class FakeOverview(Stage):
    """Thresholds the DSM into one segment."""
    kind, name = "overview", "fake"

    class Params(StageParams):
        height_m: float = Field(5.0, description="height threshold")

    @classmethod
    def scene_needs(cls, params):
        return ("dsm",)

    def __call__(self, scene, obs):
        r = load_raster(scene, "dsm")
        dsm = r.data[0]
        mask = dsm - dsm.min() > self.params.height_m
        labels = np.where(mask, 0, -1).astype(np.int32)
        rows, cols = np.nonzero(mask)
        if obs.wants_debug:
            obs.debug("dsm", DebugImage(dsm))
        return OverviewSegments(
            grid=r.grid, label_image=labels, ids=np.array([1]), boundary_px=(np.stack([rows, cols], 1),),
            centroids=r.grid.pixel_to_world(rows, cols).mean(0, keepdims=True), polygons=(None,),
            ground_height=np.array([dsm.min()]), ground_normal=np.array([[0, 0, 1.0]]), source="overview.fake")


class FakeStreet(Stage):
    """Every point in one segment."""
    kind, name = "street", "fake"

    class Params(StageParams):
        fail: bool = Field(False, description="raise a StageError")
        interrupt: bool = Field(False, description="raise KeyboardInterrupt")

    @classmethod
    def scene_needs(cls, params):
        return ("street_cloud",)

    def __call__(self, scene, capture, obs):
        if self.params.fail:
            raise StageError("no façade points found")
        if self.params.interrupt:
            raise KeyboardInterrupt
        p = capture.points
        n = len(p)
        for k in obs.progress(range(3), total=3, desc="fake"):
            obs.debug("iter", DebugScalar(float(k)), it=k, timeline="street_iter")
        return StreetSegments(
            origin=p.mean(0), up_rotation=np.eye(3), point_labels=np.zeros(n, np.int32),
            carrier=np.zeros(n, np.int32), ids=np.array([0]), boundary_xy=(p[:10, :2] - p.mean(0)[:2],),
            centroids=np.zeros((1, 2)), extent_m=np.array([10.0]), ground_z=np.array([0.0]),
            ground_normal=np.array([[0, 0, 1.0]]))


class FakeGraph(Stage):
    """A graph with no edges."""
    kind, name = "graph", "fake"

    def __call__(self, street, overview, obs):
        import networkx as nx

        z = np.zeros((0, 2), int)
        return ConjugateGraphs(nx.Graph(), nx.Graph(), z, z, z, z, np.zeros(0, int), nx.Graph())


class FakeUnary(Stage):
    """No costs."""
    kind, name = "unary", "fake"

    def __call__(self, graphs, street, overview, scene, capture, obs):
        return DataCosts(np.ones((0, 1)), np.zeros((0, 0)), np.zeros((0, 0, 2)))


class FakeMatch(Stage):
    """Matches street segment 0 with over-view segment 0."""
    kind, name = "match", "fake"

    def __call__(self, graphs, costs, obs):
        return Matches(np.zeros(0, int), np.array([0]), np.array([1.0]), np.eye(3)[None], np.array([0.1]),
                       0.0, np.zeros(1), 1, True)


class FakeRefine(Stage):
    """Translation that moves the street centroid onto the over-view centroid."""
    kind, name = "refine", "fake"

    def __call__(self, matches, street, overview, scene, capture, obs, graphs=None):
        T = np.eye(4)
        T[:2, 3] = overview.centroids[0]
        return SegmentTransforms(T[None] @ street.levelling, np.array([True]), np.zeros(1), np.ones(1))


class FakeWarp(Stage):
    """Applies segment 0's transform to every point."""
    kind, name = "warp", "fake"

    def __call__(self, transforms, street, scene, capture, obs):
        p = capture.points
        T = transforms.T[0]
        pts = p @ T[:3, :3].T + T[:3, 3]
        return Registration(pts, (), np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros(len(p), np.int32))


def fake_registry() -> Registry:
    reg = Registry(lambda: [])
    for cls in (FakeOverview, FakeStreet, FakeGraph, FakeUnary, FakeMatch, FakeRefine, FakeWarp):
        reg.add(cls)
    return reg


FAKE_RECIPE = """\
recipe: 1
name: fake
steps:
  overview: {use: overview.fake, params: {height_m: 5}}
  street: {use: street.fake}
  graph: {use: graph.fake}
  unary: {use: unary.fake}
  match: {use: match.fake}
  refine: {use: refine.fake}
  warp: {use: warp.fake}
"""
