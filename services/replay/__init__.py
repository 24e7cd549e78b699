"""Replay recorded datasets into the stack, and the paper's resource evaluation (section 5).

Core (no zenoh): `readers/` (SemanticKITTI, RELLIS-3D, ROS bags and MCAP, PLY/NPZ folders),
`prepare.py` (dataset labels -> class table, range and class filter, world frame), `player.py`
(read-ahead feed, lockstep/realtime pacing), `synthetic.py` (a synthetic RELLIS-3D-layout OS1-64
sequence). Wiring: `service.py`, `__main__.py` (`smana replay`). `bench.py` and `plots.py`:
`smana bench replay`, Figures 11 and 12.
"""
