"""A toy world defined outside smana, as a plugin would be: a flat 4 m square of grass with one
box-shaped hedge in front of where the robot starts. `sim.world = "toy_world:ToyWorld"` (with
this folder on PYTHONPATH) or `register("toy", ToyWorld)` in-process builds it."""

from __future__ import annotations

import numpy as np

from smana.services.sim.worlds import BOX, GroundModel, Primitive, World, WorldObject, WorldSource

GRASS, HEDGE = 1, 4  # ids of the garden3drms class table
BOX_CENTRE = (1.2, 0.0, 0.3)
BOX_HALF_EXTENTS = (0.25, 0.4, 0.3)


class ToyWorld(WorldSource):
    def build(self, config, classes):
        res, n = 0.1, 41  # 4 m x 4 m, centred on the origin
        ground = GroundModel((-2.0, -2.0), res, np.zeros((n, n)), np.full((n, n), GRASS, np.uint16))
        box = WorldObject("box", HEDGE, (Primitive(BOX, BOX_CENTRE, BOX_HALF_EXTENTS),))
        return World(ground, [box], classes, name="toy", seed=config.seed)
