"""The grid's optional label-distribution layers (issue 29): a grid without them, and a node never
given a distribution, read as certain; patches with and without them against a dense reference."""

from __future__ import annotations

import numpy as np

from smana.common.navgrid import FLAG_KNOWN, P_SCALE, RISK_LAYER_NAMES, RISK_LAYERS, NavGrid


def test_risk_layer_names_are_the_contract():
    assert RISK_LAYER_NAMES == ("alt_labels", "p_label", "p_alt")
    assert [np.dtype(d).str for _, d, _ in RISK_LAYERS] == ["<u2", "|u1", "|u1"]
    assert [fill for *_, fill in RISK_LAYERS] == [0, P_SCALE, 0] and P_SCALE == 255


def test_a_grid_without_risk_layers_reads_certain():
    grid = NavGrid.from_bounds((0.0, 0.0), (4.0, 4.0), 0.5, tile_size=4)
    cells = np.array([[0, 0], [3, 5]], np.int32)
    grid.apply_patch(cells, [2, 3], [0.1, 0.2], [FLAG_KNOWN, FLAG_KNOWN])
    assert not grid.has_risk()
    alt, p, pa = grid.read_risk(np.array([[0, 0], [3, 5], [7, 7], [-1, 0]]))
    assert alt.tolist() == [0] * 4 and p.tolist() == [255] * 4 and pa.tolist() == [0] * 4
    labels, p_box, alt_box = grid.box(0, 0, 8, 8, layers=("labels", "p_label", "alt_labels"))
    assert labels[3, 5] == 3 and (p_box == 255).all() and (alt_box == 0).all()
    assert p_box.shape == (8, 8) and p_box.dtype == np.uint8 and alt_box.dtype == np.uint16


def test_risk_patches_agree_with_a_dense_array_and_a_patch_without_them_makes_nodes_certain():
    rng = np.random.default_rng(3)
    grid = NavGrid.from_bounds((-2.0, 0.0), (6.0, 5.0), 0.25, tile_size=8, initial_tiles=1)
    dense = {
        "alt_labels": np.zeros(grid.shape, np.uint16),
        "p_label": np.full(grid.shape, 255, np.uint8),
        "p_alt": np.zeros(grid.shape, np.uint8),
    }
    for i in range(6):
        cells = np.stack([rng.integers(0, grid.shape[0], 50), rng.integers(0, grid.shape[1], 50)])
        cells = np.unique(cells.T, axis=0).astype(np.int32)
        k = len(cells)
        base = (rng.integers(1, 9, k), np.zeros(k), np.full(k, FLAG_KNOWN, np.uint8))
        if i % 3 == 2:  # an old patch: no distribution, its nodes become certain
            grid.apply_patch(cells, *base)
            risk = (np.zeros(k, np.uint16), np.full(k, 255, np.uint8), np.zeros(k, np.uint8))
        else:
            p = rng.integers(128, 256, k)
            risk = (
                rng.integers(0, 9, k).astype(np.uint16),
                p.astype(np.uint8),
                rng.integers(0, 256 - p).astype(np.uint8),
            )
            grid.apply_patch(cells, *base, risk=risk)
        for name, a in zip(RISK_LAYER_NAMES, risk, strict=True):
            dense[name][cells[:, 0], cells[:, 1]] = a
    assert grid.has_risk()
    got = grid.box(0, 0, *grid.shape, layers=RISK_LAYER_NAMES)
    for name, a in zip(RISK_LAYER_NAMES, got, strict=True):
        np.testing.assert_array_equal(a, dense[name], err_msg=name)
    probe = np.array([[0, 0], [5, 7], [31, 19]])
    for name, a in zip(RISK_LAYER_NAMES, grid.read_risk(probe), strict=True):
        np.testing.assert_array_equal(a, dense[name][probe[:, 0], probe[:, 1]])
