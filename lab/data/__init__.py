"""Deterministic synthetic inputs for benchmarks and tests: LiDAR scans of an analytic garden
(`scans.py`) and a RELLIS-3D-shaped dataset on disk (`synthetic.py`)."""
