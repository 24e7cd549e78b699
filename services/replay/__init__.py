"""Replay recorded datasets into the stack.

Core (no zenoh): `readers/` (SemanticKITTI, RELLIS-3D, ROS bags and MCAP, PLY/NPZ folders),
`prepare.py` (dataset labels -> class table, range and class filter, world frame), `player.py`
(read-ahead feed, lockstep/realtime pacing). Wiring: `service.py`, `__main__.py` (`smana replay`).
The paper's resource evaluation (section 5, Figures 11 and 12) is `smana bench replay`
(`lab/bench/replay.py`, figures by `lab/paper_figures.py`), on the synthetic sequence of
`lab/data/synthetic.py`.
"""
