"""Issue 29, item 1: a danger only semantics can see. The wet garden's water (class 9, kind
"forbidden") in the class table, the ground truth, the camera's labels, `smana world info` and
the label noise; the paper's world (water_share 0) stays as it was."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from smana.common.classes import ClassTable, ClassTableError
from smana.common.config.sim import CameraConfig, SimConfig
from smana.services.mapper.semantic_map import SemanticMap
from smana.services.sim.degrade import (
    GARDEN_IDS,
    WATER_ID,
    WET_CONFUSABLE,
    WET_IDS,
    LabelDegrader,
    confusion_matrix,
)
from smana.services.sim.simulation import Simulation
from smana.services.sim.world_cli import cli as world_cli
from smana.services.sim.worlds import WorldError
from smana.services.sim.worlds.garden import GardenConfig, generate
from smana.services.sim.worlds.objects import GRASS, TERRAIN, WATER

WET = ClassTable.load("garden3drms_wet")


def test_water_is_forbidden_not_an_obstacle_and_costs_infinity():
    water = WET[WATER]
    assert WATER == WATER_ID == 9 and water.name == "water" and water.forbidden
    assert WET.cost_lut[WATER] == math.inf
    assert not WET.obstacle_lut[WATER] and not WET.traversable_lut[WATER]
    assert WET.forbidden_lut[WATER] and WET.forbidden_lut.sum() == 1
    assert not ClassTable.load("garden3drms").forbidden_lut.any()
    with pytest.raises(ValueError, match="not a traversable class"):
        WET.costs({WATER: 1.0})  # a forbidden class's cost cannot be overridden
    # the mapper fuses its label like any other class
    assert WATER in SemanticMap("octree-bayes", class_table=WET).class_ids.tolist()
    bad = {"class": [{"id": 0, "name": "unknown", "kind": "unknown"}, {"id": 1, "name": "x"}]}
    with pytest.raises(ClassTableError):
        ClassTable.from_dict(bad)


def test_the_paper_world_has_no_water_and_is_the_dry_twin_of_the_wet_one():
    dry = generate(3, classes=WET)
    wet = generate(3, classes=WET, water_share=0.06)
    assert GardenConfig().water_share == 0.0
    assert not (dry.ground.classes == WATER).any()
    assert dry.summary()["water_share"] == 0.0
    # the default table's world is the same as the wet table's without water
    plain = generate(3)
    assert np.array_equal(plain.ground.classes, dry.ground.classes)
    assert np.array_equal(plain.ground.heights, wet.ground.heights)
    # water only where the dry twin had visible lawn, never on gravel, under objects or at spawn
    water = wet.ground.classes == WATER
    assert np.array_equal(wet.ground.classes[~water], dry.ground.classes[~water])
    assert (dry.top_class().data[water] == GRASS).all()
    assert len(wet.objects) == len(dry.objects)
    x, y, _ = dry.spawn_pose(0.45)
    assert wet.ground.class_at(x, y) != WATER


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_ponds_cover_the_share_asked_beside_paths_and_across_lawns(seed):
    wet = generate(seed, classes=WET, water_share=0.06)
    top = wet.top_class().data
    share = float((top == WATER).mean())
    assert 0.055 <= share <= 0.08
    assert wet.summary()["water_share"] == pytest.approx(share)
    # some ponds touch the gravel's neighbourhood, some lie out in the lawns
    from scipy import ndimage

    res = wet.ground.resolution_m
    to_path_m = ndimage.distance_transform_edt(top != TERRAIN) * res
    assert (to_path_m[top == WATER] <= 0.5).any() and (to_path_m[top == WATER] > 1.0).any()
    # the paths still join the garden: the robot can reach almost all the dry ground it could
    assert wet.reachable_fraction(0.4) > 0.9


def test_water_needs_a_table_that_has_it():
    with pytest.raises(WorldError, match="garden3drms_wet"):
        generate(0, water_share=0.05)


def test_world_info_reports_the_water_share(capsys):
    args = ["--set", "sim.garden.water_share=0.06", "--set", "general.class_table=garden3drms_wet"]
    assert world_cli(["info", *args]) == 0
    info = json.loads(capsys.readouterr().out)
    assert 0.055 <= info["water_share"] <= 0.08
    assert world_cli(["info", "--set", "sim.garden.water_share=0.06"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "garden3drms_wet" in err[0] and "Traceback" not in err[0]


def test_a_rendered_frame_labels_water_where_the_world_has_it():
    cfg = SimConfig(
        garden=GardenConfig(size_m=12.0, water_share=0.08),
        seed=1,
        noise="off",
        camera=CameraConfig(width=128, height=128),
    )
    with Simulation(cfg, classes=WET) as sim:
        world = sim.world
        top = world.top_class()
        xs, ys = top.cell_centres()
        wi, wj = np.nonzero(top.data == WATER)
        # stand on dry ground 1.5 m from a pond's cell and look at it
        k = len(wi) // 2
        tx, ty = xs[wi[k]], ys[wj[k]]
        trav = world.traversability(0.4).data & (top.data != WATER)
        gx, gy = np.meshgrid(xs, ys, indexing="ij")
        d = np.where(trav, np.abs(np.hypot(gx - tx, gy - ty) - 1.5), np.inf)
        i, j = np.unravel_index(np.argmin(d), d.shape)
        x, y = float(xs[i]), float(ys[j])
        sim.robot.reset((x, y), float(world.ground.height_at(x, y)), math.atan2(ty - y, tx - x))
        sim.step(0.3)
        f = sim.camera_frame()
    water = f.labels == WATER
    assert water.sum() > 50
    # every point labelled water lies on the ground where the raster says water, and the
    # ground points in the ponds are labelled water
    pts = f.points[water].astype(float)
    assert (world.ground.class_at(pts[:, 0], pts[:, 1]) == WATER).all()
    assert np.abs(pts[:, 2] - world.ground.height_at(pts[:, 0], pts[:, 1])).max() < 0.02
    on_ground = np.abs(f.points[:, 2] - world.ground.height_at(f.points[:, 0], f.points[:, 1]))
    in_pond = (world.ground.class_at(f.points[:, 0], f.points[:, 1]) == WATER) & (on_ground < 0.02)
    assert np.mean(f.labels[in_pond] == WATER) > 0.99


def test_the_wet_confusions_extend_table_2_and_leave_the_paper_rows_alone():
    p = 0.7
    wet = confusion_matrix(p, WET_IDS, WET_CONFUSABLE)
    assert np.allclose(wet.sum(axis=1), 1.0)
    idx = {c: k for k, c in enumerate(WET_IDS)}
    w, g, t, h = idx[WATER], idx[GRASS], idx[TERRAIN], idx[4]
    assert wet[w, w] == pytest.approx(p)
    assert wet[w, g] == pytest.approx((1 - p) / 2) and wet[w, t] == pytest.approx((1 - p) / 2)
    for row in (g, t):
        assert wet[row, w] == pytest.approx((1 - p) / 3) and wet[row, h] == pytest.approx(0.1)
    # the paper's matrix never gives water; the rows of the classes water does not touch agree
    dry = confusion_matrix(p)
    assert dry.shape == (len(GARDEN_IDS), len(GARDEN_IDS))
    assert dry[idx[GRASS], idx[TERRAIN]] == pytest.approx((1 - p) / 2)
    for c in (0, 4, 5, 6, 7, 8):
        np.testing.assert_allclose(wet[idx[c], : len(GARDEN_IDS)], dry[idx[c]])
    # drawn: water becomes grass and terrain, grass becomes water, at the rates of the rows
    deg = LabelDegrader(
        "high", np.random.default_rng(0), WET.colour_lut, ids=WET_IDS, confusable=WET_CONFUSABLE
    )
    given = deg.redraw(np.full(30000, WATER))
    assert np.mean(given == WATER) == pytest.approx(0.7, abs=0.015)
    assert np.mean(given == GRASS) == pytest.approx(0.15, abs=0.01)
    assert np.mean(given == TERRAIN) == pytest.approx(0.15, abs=0.01)
    given = deg.redraw(np.full(30000, GRASS))
    assert np.mean(given == WATER) == pytest.approx(0.1, abs=0.01)


def test_a_wet_simulation_degrades_with_the_wet_rows():
    from smana.services.sim.simulation import FrameFinisher

    wet = SimConfig(garden=GardenConfig(water_share=0.05), noise="high")
    dry = SimConfig(garden=GardenConfig(), noise="high")
    assert FrameFinisher(wet, WET.colour_lut).degrader.ids == WET_IDS
    assert FrameFinisher(dry, WET.colour_lut).degrader.ids == GARDEN_IDS
