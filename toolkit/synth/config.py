"""Every knob of the synthetic scene generator, with per-preset defaults.

``SynthConfig`` is a frozen pydantic model (``extra="forbid"``): a misspelt knob is an error that
names it. ``config_for(preset, **overrides)`` starts from a preset and applies overrides.
"""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from toolkit.errors import CrossviewError


class SynthConfig(BaseModel):
    """Knobs of ``crossview synth`` (units in the names). Defaults are the ``campus`` preset."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    # --- scene placement ---------------------------------------------------------------------
    crs: str = Field("EPSG:32617", description="projected scene CRS (UTM 17N: Columbus, OH)")
    origin_easting_m: float = Field(
        329_000.0, description="approximate easting of the scene's south-west corner (m)"
    )
    origin_northing_m: float = Field(
        4_425_000.0, description="approximate northing of the scene's south-west corner (m)"
    )
    ground_height_m: float = Field(230.0, description="terrain height at the scene origin (m)")

    # --- procedural city ---------------------------------------------------------------------
    grid_nodes_x: int = Field(9, ge=2, description="street-network nodes across (count; west-east)")
    grid_nodes_y: int = Field(8, ge=2, description="street-network nodes down (count; south-north)")
    street_spacing_m: float = Field(95.0, gt=20, description="mean distance between parallel streets (m)")
    node_jitter: float = Field(
        0.18, ge=0, le=0.35, description="node position jitter, fraction of the spacing"
    )
    city_rotation_deg: float = Field(
        12.0, ge=0, le=45, description="max rotation of the street network vs. grid north (degrees)"
    )
    removed_street_fraction: float = Field(
        0.12, ge=0, le=0.4, description="grid streets removed (0-1; bigger, irregular blocks)"
    )
    diagonal_streets: int = Field(2, ge=0, description="diagonal avenues cut through the grid (count)")
    curved_street_fraction: float = Field(0.2, ge=0, le=1, description="streets drawn as curves (0-1)")
    street_width_m: tuple[float, float] = Field(
        (12.0, 22.0), description="building-free street corridor width range (m)"
    )
    park_fraction: float = Field(0.1, ge=0, le=1, description="blocks left as parks or squares (0-1)")
    building_size_m: tuple[float, float] = Field((6.0, 80.0), description="building extent range (m)")
    building_height_m: tuple[float, float] = Field(
        (4.0, 40.0), description="building height range (m; eaves to ground)"
    )
    pitched_roof_fraction: float = Field(
        0.35, ge=0, le=1, description="low buildings with gable or hip roofs (0-1)"
    )
    terrain_slope_pct: float = Field(1.5, ge=0, le=10, description="mean terrain gradient (%)")
    terrain_undulation_m: float = Field(1.5, ge=0, description="amplitude of gentle terrain undulation (m)")
    yard_trees_per_ha: float = Field(12.0, ge=0, description="trees in yards per hectare of unbuilt block")
    park_trees_per_ha: float = Field(45.0, ge=0, description="trees per hectare in parks")
    street_tree_fraction: float = Field(0.35, ge=0, le=1, description="streets lined with trees (0-1)")
    clutter_level: float = Field(1.0, ge=0, description="multiplier on parked cars and poles along streets")

    # --- route and cameras -------------------------------------------------------------------
    route_length_m: float = Field(1500.0, gt=20, description="target vehicle route length (m)")
    route_closed: bool = Field(True, description="route ends where it started (the drift is not closed)")
    camera_step_m: float = Field(1.0, gt=0, description="distance between video frames kept as cameras (m)")
    capture_step_m: float = Field(2.0, gt=0, description="distance between ray-casting positions (m)")
    camera_height_m: float = Field(2.0, gt=0, description="camera height above the road (m)")
    lane_offset_m: float = Field(2.0, ge=0, description="vehicle offset right of the street centreline (m)")
    camera_pitch_deg: float = Field(4.0, description="camera pitch above the horizon (degrees)")
    hfov_deg: float = Field(100.0, gt=10, lt=170, description="horizontal field of view (degrees; forward camera)")
    image_width_px: int = Field(1600, ge=64, description="image width (px)")
    image_height_px: int = Field(1200, ge=64, description="image height (px)")
    ray_step_deg: float = Field(0.35, gt=0, description="angular spacing of cast rays (degrees)")
    min_range_m: float = Field(1.5, ge=0, description="nearest depth MVS reconstructs (m)")
    max_range_m: float = Field(35.0, gt=1, description="farthest depth MVS reconstructs (m)")
    min_incidence_deg: float = Field(
        8.0, ge=0, lt=90, description="grazing surfaces below this angle are not reconstructed (degrees)"
    )
    point_spacing_m: float = Field(
        0.13, gt=0, description="MVS density: at most one point per voxel of this size"
    )
    noise_m: float = Field(
        0.03, ge=0, description="MVS noise sigma at 10 m depth (grows linearly with depth)"
    )
    outlier_fraction: float = Field(
        0.02, ge=0, le=0.5, description="street points replaced by gross outliers"
    )
    chunk_route_m: float = Field(400.0, gt=10, description="route length processed per streaming chunk (m)")
    street_density_factor: int = Field(
        1, ge=1, description="street points per MVS point: extra samples of the same surface "
        "(>1: street/cloud.laz, truth for the first sample of each only)"
    )

    # --- drift and global transform ----------------------------------------------------------
    heading_walk_deg: float = Field(0.8, ge=0, description="heading random walk, deg per sqrt(100 m)")
    pitch_walk_deg: float = Field(0.12, ge=0, description="pitch random walk, deg per sqrt(100 m)")
    roll_walk_deg: float = Field(0.12, ge=0, description="roll random walk, deg per sqrt(100 m)")
    scale_drift: float = Field(
        0.008, gt=-0.5, lt=0.5, description="scale trend over the whole route (fraction); random sign unless scale_drift_signed"
    )
    scale_drift_signed: bool = Field(
        False, description="take scale_drift's sign as given (negative: the street cloud shrinks along the route)"
    )
    scale_walk: float = Field(0.0005, ge=0, description="scale random walk per sqrt(100 m) (fraction)")
    max_tilt_deg: float = Field(30.0, ge=0, le=180, description="max tilt of the street frame's up axis (degrees)")
    global_offset_m: float = Field(500.0, ge=0, description="scale of the random street-frame translation (m)")
    dem_gsd_m: float = Field(10.0, gt=0, description="cell size of overview/dem.tif, the bare-earth terrain model (m)")
    dem_noise_m: float = Field(0.3, ge=0, description="noise sigma of the terrain model's heights (m)")
    street_scale: float = Field(1.0, ge=0.01, le=100, description="scale of the street frame: cloud, COLMAP points and camera positions (truth stays metric)")

    # --- COLMAP model and GPS ------------------------------------------------------------------
    sparse_points: int = Field(30_000, ge=0, description="street points observed in the COLMAP model")
    track_length: int = Field(6, ge=2, description="max observations per sparse point")
    pixel_noise_px: float = Field(0.5, ge=0, description="2D observation noise sigma per image axis")
    gps_sigma_m: float = Field(3.0, ge=0, description="noise of street/gps.csv fixes (m)")

    # --- over-view products ------------------------------------------------------------------
    gsd_m: float = Field(0.5, gt=0, description="over-view ground sampling distance (m)")
    dsm_noise_m: float = Field(0.25, ge=0, description="DSM height noise sigma")
    dsm_edge_sigma_px: float = Field(1.2, ge=0, description="stereo-like smoothing of DSM edges (px)")
    dsm_hole_fraction: float = Field(
        0.002, ge=0, le=0.2, description="DSM area lost to matching failures (0-1; nodata)"
    )
    sun_azimuth_deg: float = Field(150.0, description="sun azimuth (degrees; clockwise from north)")
    sun_elevation_deg: float = Field(45.0, gt=1, le=90, description="sun elevation (degrees)")
    ortho_noise: float = Field(6.0, ge=0, description="orthophoto texture noise (digital numbers)")
    footprint_shift_m: float = Field(0.7, ge=0, description="OSM-like footprint shift sigma")
    footprint_missing_fraction: float = Field(
        0.04, ge=0, le=1, description="buildings missing from footprints (0-1)"
    )
    footprint_merged_fraction: float = Field(
        0.05, ge=0, le=1, description="neighbouring buildings merged in footprints (0-1)"
    )
    label_edge_px: int = Field(2, ge=0, description="label-map edge erosion/dilation up to this many pixels")
    label_false_blobs_per_ha: float = Field(0.3, ge=0, description="false building blobs in the label map per hectare")
    label_missed_fraction: float = Field(0.04, ge=0, le=1, description="buildings missed by the label map (0-1)")
    spurious_overview_fraction: float = Field(
        0.0, ge=0, le=2, description="extra over-view-only buildings (0-1; demolished since)"
    )
    missing_building_fraction: float = Field(
        0.0, ge=0, le=1, description="buildings absent from every over-view product (0-1; new)"
    )
    overview_cloud_step_px: int = Field(
        1, ge=1, description="over-view cloud: one point per this many DSM pixels"
    )
    margin_m: float = Field(40.0, ge=0, description="over-view margin around the city (m)")

    # --- truth --------------------------------------------------------------------------------
    lidar_spacing_m: float = Field(0.25, gt=0, description="truth/lidar.ply point spacing")
    lidar_corridor_m: float = Field(45.0, gt=0, description="truth/lidar.ply half-width around the route (m)")

    # --- real cities (--city) ------------------------------------------------------------------
    default_levels: tuple[int, int] = Field(
        (2, 6), description="building:levels range sampled when OSM has no height (count)"
    )
    level_height_m: float = Field(3.0, gt=0, description="storey height for building:levels (m)")
    city_crop_m: float = Field(
        0.0, ge=0, description="keep real-city buildings within a square this wide around the centre (m; 0: all)"
    )
    city_crop_centre_lonlat: tuple[float, float] | None = Field(
        None, description="centre of the city_crop_m square as WGS84 (lon, lat); None: the buildings' median centre"
    )

    # --- output --------------------------------------------------------------------------------
    preview: bool = Field(True, description="draw preview.png")

    @model_validator(mode="after")
    def _consistent(self) -> SynthConfig:
        if self.scale_drift < 0 and not self.scale_drift_signed:
            raise ValueError("a negative scale_drift needs scale_drift_signed=true (else its sign is random)")
        if self.city_crop_centre_lonlat is not None:
            lon, lat = self.city_crop_centre_lonlat
            if not (-180 <= lon <= 180 and -90 <= lat <= 90):
                raise ValueError(f"city_crop_centre_lonlat {lon, lat} is not a WGS84 (lon, lat)")
            if self.city_crop_m <= 0:
                raise ValueError("city_crop_centre_lonlat needs city_crop_m > 0 (the size of the crop)")
        return self


PRESETS: dict[str, dict[str, Any]] = {
    "tiny": dict(
        grid_nodes_x=4,
        grid_nodes_y=3,
        street_spacing_m=75.0,
        diagonal_streets=1,
        removed_street_fraction=0.0,
        route_length_m=200.0,
        route_closed=False,
        park_fraction=0.1,
        point_spacing_m=0.22,
        ray_step_deg=0.5,
        capture_step_m=2.0,
        sparse_points=4000,
        margin_m=30.0,
        max_range_m=30.0,
        lidar_spacing_m=0.3,
    ),
    "campus": {},
    "district": dict(
        grid_nodes_x=20,
        grid_nodes_y=18,
        route_length_m=5000.0,
        route_closed=True,
        point_spacing_m=0.11,
        ray_step_deg=0.3,
        sparse_points=60_000,
        overview_cloud_step_px=2,
        chunk_route_m=250.0,
        lidar_spacing_m=0.35,
    ),
}


def config_for(preset: str, **overrides: Any) -> SynthConfig:
    """The preset's config with ``overrides`` applied; one-line errors for bad names or values."""
    if preset not in PRESETS:
        raise CrossviewError(f"synth: unknown preset {preset!r} (choose from {', '.join(PRESETS)})")
    values = {**PRESETS[preset], **overrides}
    try:
        return SynthConfig(**values)
    except ValidationError as exc:
        err = exc.errors()[0]
        where = ".".join(str(p) for p in err["loc"])
        msg = err["msg"].removeprefix("Value error, ")
        raise CrossviewError(f"synth: {where}: {msg}" if where else f"synth: {msg}") from None
