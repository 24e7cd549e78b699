"""The shared tiled grid: patches in, boxes and exports out, against a dense reference array."""

from __future__ import annotations

import numpy as np
import pytest

from smana.common.navgrid import FLAG_KNOWN, FLAG_OBSTACLE, NavGrid


def random_patch(rng, shape, k):
    cells = np.stack([rng.integers(0, shape[0], k), rng.integers(0, shape[1], k)], 1)
    cells = np.unique(cells, axis=0).astype(np.int32)
    labels = rng.integers(0, 9, len(cells)).astype(np.uint16)
    heights = rng.normal(size=len(cells)).astype(np.float32)
    flags = rng.choice([FLAG_KNOWN, FLAG_KNOWN | FLAG_OBSTACLE], len(cells)).astype(np.uint8)
    return cells, labels, heights, flags


def test_patches_boxes_and_export_agree_with_a_dense_array():
    rng = np.random.default_rng(0)
    grid = NavGrid.from_bounds((-3.0, 2.0), (7.0, 9.0), 0.25, tile_size=8, initial_tiles=1)
    assert grid.shape == (40, 28)
    dense_l = np.zeros(grid.shape, np.uint16)
    dense_h = np.full(grid.shape, np.nan, np.float32)
    dense_f = np.zeros(grid.shape, np.uint8)
    for _ in range(5):
        cells, labels, heights, flags = random_patch(rng, grid.shape, 60)
        assert grid.apply_patch(cells, labels, heights, flags) == 0
        dense_l[cells[:, 0], cells[:, 1]] = labels
        dense_h[cells[:, 0], cells[:, 1]] = heights
        dense_f[cells[:, 0], cells[:, 1]] = flags
    for box in [(0, 0, 40, 28), (3, 5, 17, 9), (-5, -5, 100, 100), (39, 27, 40, 28)]:
        got = grid.box(*box)
        sx = slice(max(0, box[0]), min(40, box[2]))
        sy = slice(max(0, box[1]), min(28, box[3]))
        np.testing.assert_array_equal(got[0], dense_l[sx, sy])
        np.testing.assert_array_equal(got[1], dense_h[sx, sy])
        np.testing.assert_array_equal(got[2], dense_f[sx, sy])
    cells, labels, heights, flags = grid.export()
    want = np.argwhere(dense_f != 0)
    assert sorted(map(tuple, cells.tolist())) == sorted(map(tuple, want.tolist()))
    np.testing.assert_array_equal(labels, dense_l[cells[:, 0], cells[:, 1]])
    np.testing.assert_array_equal(heights, dense_h[cells[:, 0], cells[:, 1]])
    rl, rh, rf = grid.read_cells(np.array([[0, 0], [-1, 3], [39, 27], [40, 0]]))
    assert rl[1] == 0 and np.isnan(rh[1]) and rf[3] == 0


def test_world_cells_round_trip_and_out_of_bounds():
    grid = NavGrid.from_bounds((-1.0, -1.0), (1.0, 1.0), 0.2)
    ix, iy, ok = grid.world_to_cell(np.array([[-0.99, 0.95], [1.0, 0.0], [np.nan, 0.0]]))
    assert ok.tolist() == [True, False, False]
    assert (ix[0], iy[0]) == (0, 9)
    np.testing.assert_allclose(grid.cell_centre(0, 9), [-0.9, 0.9])
    assert (
        grid.apply_patch(
            np.array([[0, 0], [10, 0]]), np.zeros(2), np.zeros(2), np.ones(2, np.uint8)
        )
        == 1
    )
    with pytest.raises(ValueError, match="same length"):
        grid.apply_patch(np.array([[0, 0]]), np.zeros(2), np.zeros(1), np.zeros(1))
    with pytest.raises(ValueError, match="integer"):
        grid.apply_patch(np.zeros((1, 2)), np.zeros(1), np.zeros(1), np.zeros(1))
    with pytest.raises(ValueError, match="exceed"):
        NavGrid.from_bounds((1, 1), (0, 2), 0.2)


def test_memory_grows_with_tiles_not_bounds():
    grid = NavGrid.from_bounds((-1000, -1000), (1000, 1000), 0.2, tile_size=32)
    empty = grid.nbytes
    assert empty < 2_000_000  # 10^8 nodes of bounds, ~98k tiles of 4-byte map entries
    grid.apply_patch(np.array([[5000, 5000]]), [1], [0.0], [FLAG_KNOWN])
    assert grid.n_tiles == 1 and grid.known_box() == (4992, 4992, 5024, 5024)
