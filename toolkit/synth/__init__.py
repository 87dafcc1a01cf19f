"""Synthetic scenes with exact truth: ``crossview synth`` (procedural city or a real city model).

Entry points: ``toolkit.synth.generate.generate(preset, seed, out)``,
``generate_from_city(path, seed, out)``, the ``SynthConfig`` knobs and ``command.register``.

Modules: ``config`` (knobs, presets) · ``streets``/``city``/``clutter``/``mesh``/``world`` (the
procedural world) · ``realcity``/``openspace`` (CityJSON / OSM worlds, routes through open space) ·
``route`` (vehicle route and true cameras) · ``raycast`` (Open3D ray casting) · ``street`` (MVS-like
capture) · ``drift`` · ``colmap_model`` · ``overview``/``footprints`` (over-view products) ·
``overview_writer``/``street_writer``/``density``/``files`` (writing, streaming) · ``preview`` · ``generate``.

Truth of the street cloud
-------------------------
``truth/street_points.npy`` (N,3) float64 holds, row for row with ``street/cloud.ply``, where each
street point is in the scene CRS *without* drift and global transform (the MVS noise and the
outliers are part of the point: a perfect registration maps the cloud exactly onto this array).
``truth/street_labels.npy`` (N,) int32: building id (= ``id`` in ``truth/buildings.geojson``), -1
ground, -2 clutter (trees, cars, poles) and outliers.

``truth/drift.npz`` records the distortion (C cameras, frame k = ``frame_{k:06d}.jpg``):

- ``true_centres`` (C,3): true camera centres c_k, scene CRS.
- ``drift_centres`` (C,3): drifted centres c'_k, scene CRS before the global transform.
- ``drift_rotation`` (C,3,3) D_k and ``drift_scale`` (C,) s_k: the drift similarity of camera k.
- ``global_rotation`` (3,3) G_R, ``global_translation`` (3,) G_t and ``global_scale`` k
  (``street_scale``): the street frame.
- ``camera_index`` (N,) int32: the camera k whose drift each street point carries.
- ``sparse_point_index`` (P,) int64: street-point row of each COLMAP point (its id is row + 1).

``street_density_factor`` K > 1 (``density``) writes each of the N MVS points as K consecutive rows
of ``street/cloud.laz``: row i*K is point i of the K = 1 scene, rows i*K+1 … i*K+K-1 extra samples of
its surface. The truth arrays above (``camera_index`` and ``sparse_point_index`` included) stay the
K = 1 scene's, N rows, and ``truth/street_rows.npy`` (N,) int64 = i*K names the cloud row of each; a
COLMAP point's id is street_rows[sparse_point_index] + 1.

A street point with true position x and camera k is written as
``x_street = k (G_R (c'_k + s_k D_k (x - c_k)) + G_t)``; ``toolkit.synth.drift.Drift.apply`` / ``undo``
implement both directions. ``street/sparse`` holds the drifted cameras in the street frame
(``R = R_true D_k^T G_R^T``); its 2D observations are projections of the true points by the true
cameras (``truth/cameras.txt``) plus Gaussian noise of ``pixel_noise_px`` per image axis.

``truth/buildings.geojson`` lists the buildings of the street epoch (property ``in_overview``
false for those removed from the over-view products by ``missing_building_fraction``); over-view-
only (spurious) buildings are not in it. ``overview/footprints.geojson`` and ``map.osm`` use their
own OSM-like ids.
"""
