"""The simulator: a PyBullet garden world standing in for the paper's Ignition Gazebo one.

Core (no zenoh): `worlds` (kinds of world behind a registry, and the `World` they build, with its
ground truth), `simulation.Simulation` (physics, robot, camera, LiDAR, degradation). Service:
`service.SimService` (`smana sim`). Tool: `smana world ...` (`world_cli`). The benchmark is
`smana bench sim` (lab/bench/sim.py).
"""
