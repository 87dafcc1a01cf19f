"""toolkit.open3d_import: Open3D without its plotly/dash viewer, which still works when called."""

import subprocess
import sys

import pytest

pytest.importorskip("open3d")

CHILD = """
import sys
from toolkit.open3d_import import open3d
o3d = open3d()
import numpy as np
pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.random.default_rng(0).random((200, 3))))
pc.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(10))
assert np.asarray(pc.normals).shape == (200, 3)
print("dash" in sys.modules, "plotly" in sys.modules)
fig = o3d.visualization.get_plotly_fig([pc])
print("dash" in sys.modules, type(fig).__name__)
"""


def test_open3d_imports_without_dash_and_the_viewer_still_works():
    out = subprocess.run([sys.executable, "-c", CHILD], capture_output=True, text=True, check=True).stdout.split("\n")
    assert out[0] == "False False"  # the stand-in kept dash and plotly out
    assert out[1] == "True Figure"  # the first call imported the real module


def test_open3d_returns_the_module_already_imported():
    from toolkit.open3d_import import open3d

    o3d = open3d()
    assert open3d() is o3d is sys.modules["open3d"]
