"""Small synthetic inputs for tests and benchmarks (never used by a run): toy street and over-view
segments (``matching_toy``), toy façade clouds (``street_toy``) and random matching problems with a
known labelling (``solvers_synth``)."""
