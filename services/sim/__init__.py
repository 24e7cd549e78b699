"""The simulator: a PyBullet garden world standing in for the paper's Ignition Gazebo one.

Core (no zenoh): `world.GardenWorld` (worlds and their ground truth), `simulation.Simulation`
(physics, robot, camera, LiDAR, degradation). Service: `service.SimService` (`smana sim`).
Tools: `smana world ...` (`world_cli`), `smana bench sim` (`bench`).
"""
