"""The run's StreetCapture (the street side in metres) and RunOutputs (what the stages are given)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from toolkit.capture import StreetCapture
from toolkit.io.cloud import read_points
from toolkit.io.colmap import read_model
from toolkit.scene import load_cloud, load_scene
from toolkit.stage import KIND_INPUTS, KIND_OPTIONAL, KIND_OUTPUT, RUN_INPUTS
from toolkit.street_scale import resolve_street_scale
from toolkit.types import RunOutputs


def test_the_capture_is_the_street_side_in_metres(mini_scene: Path):
    scene = resolve_street_scale(load_scene(mini_scene), 2.0)
    capture = StreetCapture(scene)
    raw = read_points(mini_scene / "street/cloud.ply")
    np.testing.assert_array_equal(capture.points, raw / 2.0)
    assert not capture.points.flags.writeable
    model = read_model(mini_scene / "street/sparse")
    np.testing.assert_array_equal(capture.sparse.centres, model.centres / 2.0)
    assert capture.sparse.image_names == model.image_names
    assert capture.gps is None and capture.gps_path is None and capture.scale.value == 2.0
    source = capture.attributes()       # as written: the street frame's own units
    assert source.count == len(raw)
    np.testing.assert_array_equal(next(source.chunks()).xyz, raw)


def test_a_capture_without_a_model_has_none_and_says_who_needs_it(mini_scene: Path):
    from toolkit.errors import SceneError

    scene = load_scene(mini_scene)
    bare = StreetCapture(dataclasses.replace(scene, files=dataclasses.replace(scene.files, sparse=None)))
    assert bare.sparse is None and bare.sparse_path is None
    with pytest.raises(SceneError, match="adjust needs street.sparse"):
        bare.require_sparse("adjust")


def test_the_street_cloud_is_not_read_around_the_capture(mini_scene: Path):
    with pytest.raises(ValueError, match="StreetCapture"):
        load_cloud(load_scene(mini_scene), "street_cloud")


def test_every_stage_input_is_a_field_of_the_run_outputs():
    fields = {f.name for f in dataclasses.fields(RunOutputs)}
    names = set(RUN_INPUTS) | set(KIND_OUTPUT.values())
    assert fields == names
    for kind in KIND_INPUTS:
        assert set(KIND_INPUTS[kind]) | set(KIND_OPTIONAL.get(kind, ())) <= fields, kind
    made = RunOutputs(street=object())
    assert made.has("street") and not made.has("overview") and made.made() == ("street",)
