"""Replay recorded datasets into the stack, and the paper's resource evaluation (section 5).

`readers/` reads SemanticKITTI, RELLIS-3D, ROS bags / MCAP and folders of PLY or NPZ scans;
`prepare.py` maps dataset labels to a class table and filters the points; `synthetic.py` writes a
synthetic RELLIS-3D-layout sequence; `service.py` publishes scans and poses over Zenoh.
"""
