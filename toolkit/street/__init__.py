"""Street-view building segmentation helpers (Ling & Qin 2022, street-view building segments), used by ``street.region_growing``."""
