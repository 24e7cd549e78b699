"""Simulator worlds: procedural gardens, their ground truth, PLY in and out, the world CLI."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from smana.services.sim.labelled_ply import PlyError, read_labelled_ply, write_labelled_ply
from smana.services.sim.world_cli import cli as world_cli
from smana.services.sim.worlds import BOX, SPHERE, GroundModel, Primitive, World, WorldError
from smana.services.sim.worlds.cloud import from_cloud, from_ply
from smana.services.sim.worlds.garden import generate

GROUND_IDS = (1, 2)


@pytest.fixture(scope="module")
def world() -> World:
    return generate(seed=3, layout="classic")


@pytest.fixture(scope="module")
def small_world() -> World:
    return generate(seed=5, size_m=6.0, layout="classic")


def test_same_seed_same_world_other_seed_other_world(world):
    again = generate(seed=3, layout="classic")
    assert np.array_equal(again.ground.heights, world.ground.heights)
    assert np.array_equal(again.ground.classes, world.ground.classes)
    assert [o.primitives for o in again.objects] == [o.primitives for o in world.objects]
    other = generate(seed=4, layout="classic")
    assert not np.array_equal(other.ground.heights, world.ground.heights)


def test_classic_world_is_a_12m_garden_with_scattered_objects(world):
    assert world.bounds == pytest.approx((-6.0, -6.0, 6.0, 6.0))
    kinds = {o.kind for o in world.objects}
    assert {"wall", "hedge", "rose", "obstacle"} <= kinds
    assert {o.class_id for o in world.objects} >= {4, 6, 7}
    ground = world.ground.classes
    assert 0.4 < np.mean(ground == 2) < 0.6  # terrain and grass in about equal parts
    # about half the ground is free for a robot of 0.3 m radius, and that free space is connected
    assert 0.7 < world.free_fraction() < 0.95
    free = world.traversability(0.3).data
    assert 0.4 < free.mean() < 0.7
    labelled, n = ndimage.label(free)
    sizes = np.bincount(labelled.ravel())[1:]
    assert sizes.max() / sizes.sum() > 0.99
    # slopes stay gentle
    gx, gy = np.gradient(world.ground.heights, world.ground.resolution_m)
    assert np.hypot(gx, gy).max() <= 0.15 + 1e-9


def test_spawn_pose_is_free(world):
    x, y, z = world.spawn_pose(0.45)
    assert world.traversability(0.45).at(x, y)
    assert abs(x) < 1.5 and abs(y) < 1.5
    assert z == pytest.approx(float(world.ground.height_at(x, y)))


def test_bigger_worlds_scale(world):
    big = generate(seed=1, size_m=30.0, ground_resolution_m=0.2, layout="classic")
    assert big.bounds == pytest.approx((-15.0, -15.0, 15.0, 15.0))
    n_big = sum(o.kind != "wall" for o in big.objects)
    n_small = sum(o.kind != "wall" for o in world.objects)
    assert n_big > 4 * n_small


def test_bad_spec_is_refused():
    with pytest.raises(WorldError, match="clutter"):
        generate(seed=0, clutter=1.5)
    with pytest.raises(WorldError, match="size_m"):
        generate(seed=0, size_m=0.5)


def test_ground_interpolation_is_exact_on_vertices_and_planes():
    heights = np.add.outer(np.arange(4) * 0.1, np.arange(3) * -0.2)  # a plane
    ground = GroundModel((0.0, 0.0), 0.5, heights, np.ones((4, 3), np.uint16))
    x = np.random.default_rng(0).uniform(0, 1.5, 100)
    y = np.random.default_rng(1).uniform(0, 1.0, 100)
    assert np.allclose(ground.height_at(x, y), x / 0.5 * 0.1 - y / 0.5 * 0.2)
    bump = np.zeros((3, 3))
    bump[1, 1] = 1.0
    ground = GroundModel((0.0, 0.0), 1.0, bump, np.ones((3, 3), np.uint16))
    assert ground.height_at(1.0, 1.0) == pytest.approx(1.0)
    # the cell (0,0)-(1,1) is split along (1,0)-(0,1): below that diagonal (1,1) has no weight
    assert ground.height_at(0.3, 0.3) == pytest.approx(0.0)
    assert ground.height_at(0.7, 0.7) == pytest.approx(0.4)


def test_gt_cloud_lies_on_surfaces_with_their_labels(small_world):
    w = small_world
    pts, labels = w.gt_cloud(0.05)
    assert pts.dtype == np.float32 and labels.dtype == np.uint16 and len(pts) == len(labels)
    p64 = pts.astype(np.float64)
    on_ground = np.isin(labels, GROUND_IDS)
    dz = np.abs(p64[on_ground, 2] - w.ground.height_at(p64[on_ground, 0], p64[on_ground, 1]))
    assert dz.max() < 1e-4
    assert np.array_equal(
        labels[on_ground], w.ground.class_at(p64[on_ground, 0], p64[on_ground, 1])
    )
    obj = p64[~on_ground]
    # slow, obvious check: an object point is on the boundary of an object of its class, i.e.
    # inside that object grown by 1 mm and inside no object shrunk by 1 mm
    grown = np.zeros(len(obj), np.uint16)
    for o in w.objects:
        grown[o.contains(obj, margin=-1e-3)] = o.class_id
    assert np.array_equal(grown, labels[~on_ground])
    for o in w.objects:
        assert not o.contains(p64, margin=1e-3).any()
    # every object shows some surface
    for o in w.objects:
        assert o.contains(obj, margin=-1e-3).any(), o.kind


def test_top_class_matches_a_column_march(small_world):
    """Reference: walk down a column of points from above until one is inside an object. Cells
    on an object's edge (where growing or shrinking the objects by 1 mm changes the answer) are
    ambiguous and left out."""
    w = small_world
    top = w.top_class()
    xs, ys = top.cell_centres()
    rng = np.random.default_rng(0)
    ii = rng.integers(0, len(xs), 300)
    jj = rng.integers(0, len(ys), 300)
    zs = np.arange(4.0, -1.0, -0.005)

    def march(i, j, grow):
        column = np.column_stack([np.full_like(zs, xs[i]), np.full_like(zs, ys[j]), zs])
        hit = w.object_class_at(column[zs > w.ground.heights[i, j]], grow_m=grow)
        inside = np.flatnonzero(hit)
        return int(hit[inside[0]]) if len(inside) else int(w.ground.classes[i, j])

    compared = agree = 0
    for i, j in zip(ii, jj, strict=True):
        expected = march(i, j, 1e-3)
        if expected != march(i, j, -1e-3):
            continue
        compared += 1
        agree += int(top.data[i, j]) == expected
    assert compared > 250
    assert agree == compared


def test_traversability_with_radius_is_a_subset():
    w = generate(seed=7, size_m=8.0, layout="classic")
    t0, t3 = w.traversability(0.0).data, w.traversability(0.3).data
    assert np.all(t0[t3]) and t3.sum() < t0.sum()
    assert not t0[w.top_class().data == 8].any()  # under a tree crown is not traversable


def test_ply_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(500, 3)).astype(np.float32)
    labels = rng.integers(0, 9, 500).astype(np.uint16)
    colours = rng.integers(0, 256, (500, 3)).astype(np.uint8)
    path = tmp_path / "c.ply"
    write_labelled_ply(path, pts, labels, colours)
    back, back_labels = read_labelled_ply(path)
    assert np.array_equal(back.astype(np.float32), pts)
    assert np.array_equal(back_labels, labels)
    header = path.read_bytes()[:300].decode("ascii", "replace")
    assert "binary_little_endian" in header and "property int label" in header


def test_ply_reader_ascii_and_errors(tmp_path):
    p = tmp_path / "a.ply"
    p.write_text(
        "ply\nformat ascii 1.0\nelement vertex 2\nproperty double x\nproperty double y\n"
        "property double z\nproperty float class\nend_header\n0 1 2 4\n3 4 5 6\n"
    )
    pts, labels = read_labelled_ply(p)
    assert pts.tolist() == [[0, 1, 2], [3, 4, 5]] and labels.tolist() == [4, 6]
    with pytest.raises(PlyError, match="vertex property .label. missing"):
        read_labelled_ply(p, label_field="label")
    bad = tmp_path / "b.ply"
    bad.write_bytes(
        b"ply\nformat binary_little_endian 1.0\nelement vertex 10\nproperty float x\n"
        b"property float y\nproperty float z\nproperty uchar label\nend_header\n" + b"\0" * 20
    )
    with pytest.raises(PlyError, match="truncated"):
        read_labelled_ply(bad)
    with pytest.raises(PlyError, match="not a PLY"):
        (tmp_path / "c.ply").write_text("hello")
        read_labelled_ply(tmp_path / "c.ply")


def _toy_cloud(spacing: float = 0.04) -> tuple[np.ndarray, np.ndarray]:
    """Flat 4 m x 4 m ground (grass for x < 0, terrain for x >= 0), a hedge box, a rose ball."""
    g = np.arange(-2.0, 2.0, spacing) + spacing / 2
    gx, gy = (a.ravel() for a in np.meshgrid(g, g, indexing="ij"))
    ground = np.column_stack([gx, gy, 0.02 * gx])
    ground_labels = np.where(gx < 0, 1, 2)
    hedge = Primitive(BOX, (-1.0, 0.5, 0.5), (0.6, 0.25, 0.5)).sample_surface(spacing)
    rose = Primitive(SPHERE, (1.0, -1.0, 0.3), (0.25, 0.25, 0.25)).sample_surface(spacing)
    pts = np.concatenate([ground, hedge, rose])
    labels = np.concatenate([ground_labels, np.full(len(hedge), 4), np.full(len(rose), 6)])
    return pts, labels


def test_world_from_cloud_reproduces_classes(tmp_path):
    pts, labels = _toy_cloud()
    path = tmp_path / "toy.ply"
    colours = np.zeros((len(pts), 3), np.uint8)
    write_labelled_ply(path, pts, labels.astype(np.uint16), colours)
    w = from_ply(path, voxel_m=0.05)
    assert sorted(o.class_id for o in w.objects if o.kind == "voxels") == [4, 6]
    assert w.ground.class_at(-1.5, -1.5) == 1 and w.ground.class_at(1.5, 1.5) == 2
    assert w.ground.height_at(1.0, 0.0) == pytest.approx(0.02, abs=0.01)
    top = w.top_class()
    assert top.at(-1.0, 0.5) == 4 and top.at(1.0, -1.0) == 6 and top.at(0.5, 1.5) == 2
    assert top.at(-1.5, -1.5) == 1
    # the hedge voxels fill its surface shell: a point on the surface is inside a voxel
    hedge = next(o for o in w.objects if o.class_id == 4)
    assert hedge.contains(np.array([[-1.0, 0.25, 0.5], [-1.6, 0.5, 0.5]])).all()
    assert not hedge.contains(np.array([[1.0, 1.0, 0.5]])).any()
    gt_pts, gt_labels = w.gt_cloud()
    assert np.isin([1, 2, 4, 6, 7], gt_labels).all()  # the source cloud plus the walls
    with pytest.raises(WorldError, match="traversable"):
        from_cloud(pts[labels == 4], labels[labels == 4])


def test_world_cli_export_and_preview(tmp_path, capsys):
    out = tmp_path / "gt.ply"
    assert (
        world_cli(["export", "--seed", "2", "--size", "5", "--spacing", "0.1", "--out", str(out)])
        == 0
    )
    pts, labels = read_labelled_ply(out)
    assert len(pts) > 1000 and set(np.unique(labels)) <= {1, 2, 4, 5, 6, 7, 8}
    png = tmp_path / "w.png"
    assert world_cli(["preview", "--seed", "2", "--size", "5", "--out", str(png)]) == 0
    import cv2

    img = cv2.imread(str(png))
    assert img is not None and img.shape[0] >= 500
    assert (
        world_cli(["preview", "--seed", "2", "--size", "5", "--out", str(tmp_path / "x.nope")]) == 2
    )
    assert world_cli(["info", "--seed", "2", "--size", "5"]) == 0
    assert '"free_fraction"' in capsys.readouterr().out
