"""A toy world with parameters of its own, from outside smana: a flat square of grass with
`count` hedge pillars of half-width `radius_m` on a circle of `ring_m` around the start.

It is what a world plugin with knobs looks like: this one file, no edit of smana. Its knobs are a
config `Section` declared beside it (`config_key`, `config_class`), read from `[sim.pillars]`
(TOML or `--set sim.pillars.count=5`) once the world is named, by spec (`sim.world =
"tests.support.toy_pillars_world:Pillars"`) or after `worlds.register("pillars", Pillars)`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from smana.common.config import Section, param
from smana.services.sim.worlds import BOX, GroundModel, Primitive, World, WorldObject, WorldSource

GRASS, HEDGE = 1, 4  # ids of the garden3drms class table
HEIGHT_M = 0.8


@dataclass
class PillarsConfig(Section, section="sim.pillars"):
    count: int = param(3, ge=1, le=12)
    radius_m: float = param(0.15, gt=0, le=0.5)  # half the side of a (square) pillar
    ring_m: float = param(1.5, ge=1.0, le=4.0)  # distance of the pillars from the start


def pillar_centres(p: PillarsConfig) -> list[tuple[float, float]]:
    angles = [2 * math.pi * i / p.count for i in range(p.count)]
    return [(p.ring_m * math.cos(a), p.ring_m * math.sin(a)) for a in angles]


class Pillars(WorldSource):
    config_key = "pillars"
    config_class = PillarsConfig

    def build(self, config, classes):
        p = config.pillars  # this world's own section, as it is
        res, half = 0.1, p.ring_m + 1.0
        n = int(round(2 * half / res)) + 1
        ground = GroundModel(
            (-half, -half), res, np.zeros((n, n)), np.full((n, n), GRASS, np.uint16)
        )
        r = p.radius_m
        objects = [
            WorldObject(f"pillar{i}", HEDGE, (Primitive(BOX, (x, y, HEIGHT_M / 2), (r, r, 0.4)),))
            for i, (x, y) in enumerate(pillar_centres(p))
        ]
        return World(ground, objects, classes, name="pillars", seed=config.seed)
