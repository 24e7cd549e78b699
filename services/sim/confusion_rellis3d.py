"""The "realistic" label noise's confusion matrix: a published segmentation network's, measured
on an outdoor off-road dataset, mapped onto the garden's classes.

Source: P. Jiang, P. Osteen, M. Wigness, S. Saripalli, "RELLIS-3D Dataset: Data, Benchmarks and
Analysis", ICRA 2021 (arXiv:2011.12954). The network is HRNet+OCR on the RELLIS-3D image test
split, the image benchmark table's first row (mIoU 48.83 %); its row-normalised pixel confusion
matrix is the one the dataset's repository publishes with that evaluation
(github.com/unmannedlab/RELLIS-3D, `utils/Evaluate_img.ipynb`, the heat map printed after the
per-class IoU 0.00 & 90.20 & 80.53 ..., two decimals). `RELLIS3D_HRNET_ROWS` holds the rows the
garden needs, as published (a row sums to 0.99-1.00: rounding).

The mapping (docs/tutorial.md says the same):

- true classes: grass <- grass; terrain (gravel paths, plazas, bare soil) <- the mean of concrete,
  asphalt and mud; hedge, topiary, rose <- bush; obstacle (rocks, boxes) <- the mean of object
  and rubble; tree <- tree; water (the wet garden's flat ponds) <- puddle. Means weigh each row
  equally (the repository gives no pixel counts per row).
- predicted classes: grass -> grass; concrete, asphalt, mud -> terrain; puddle -> water in the
  wet garden, terrain in the dry one; tree -> tree; object, barrier, rubble -> obstacle; sky ->
  no class of the garden (a sky pixel carries no point): its share is dropped and the row
  renormalised.
- bush -> hedge, topiary, rose. RELLIS-3D has one bush class; how a network tells the garden's
  three shrubs apart is not measured there. The rule: a bush prediction on a true shrub keeps
  its class but for `shrub_swap()` to each of the other two, the mean rate at which the same
  network swaps RELLIS-3D's two woody classes (tree -> bush 0.08 of 0.96, bush -> tree 0.03 of
  0.93: 0.058); a bush prediction on any other class goes to the three shrubs equally.
"""

from __future__ import annotations

import numpy as np

# HRNet+OCR on RELLIS-3D's image test split: P(predicted | true), the published rows (see above).
RELLIS3D_HRNET_ROWS: dict[str, dict[str, float]] = {
    "grass": {"grass": 0.94, "bush": 0.05, "mud": 0.01},
    "tree": {"sky": 0.03, "tree": 0.88, "bush": 0.08},
    "bush": {"grass": 0.06, "tree": 0.03, "sky": 0.01, "bush": 0.90},
    "concrete": {"grass": 0.02, "tree": 0.01, "bush": 0.07, "concrete": 0.89},
    "asphalt": {"grass": 0.03, "asphalt": 0.34, "concrete": 0.62},
    "mud": {"grass": 0.39, "puddle": 0.01, "mud": 0.60},
    "puddle": {"grass": 0.13, "puddle": 0.79, "mud": 0.08},
    "object": {
        "grass": 0.04,
        "tree": 0.07,
        "sky": 0.01,
        "object": 0.71,
        "bush": 0.07,
        "concrete": 0.06,
        "barrier": 0.03,
    },
    "rubble": {"grass": 0.05, "bush": 0.25, "rubble": 0.70},
}

GRASS, TERRAIN, HEDGE, TOPIARY, ROSE, OBSTACLE, TREE, WATER = 1, 2, 4, 5, 6, 7, 8, 9
SHRUBS = (HEDGE, TOPIARY, ROSE)
# the garden's true classes and the RELLIS-3D rows each one is the mean of
TRUE_FROM = {
    GRASS: ("grass",),
    TERRAIN: ("concrete", "asphalt", "mud"),
    HEDGE: ("bush",),
    TOPIARY: ("bush",),
    ROSE: ("bush",),
    OBSTACLE: ("object", "rubble"),
    TREE: ("tree",),
    WATER: ("puddle",),
}
# RELLIS-3D's predicted classes -> the garden's ("bush" is split over SHRUBS, "sky" dropped)
PREDICTED_AS = {
    "grass": GRASS,
    "concrete": TERRAIN,
    "asphalt": TERRAIN,
    "mud": TERRAIN,
    "puddle": WATER,
    "tree": TREE,
    "object": OBSTACLE,
    "barrier": OBSTACLE,
    "rubble": OBSTACLE,
}


def shrub_swap(rows: dict[str, dict[str, float]] = RELLIS3D_HRNET_ROWS) -> float:
    """How often the network calls one woody class the other, given it calls it one of the two:
    the mean of tree -> bush and bush -> tree (the rate a shrub goes to each other shrub)."""
    t, b = rows["tree"], rows["bush"]
    return 0.5 * (t["bush"] / (t["bush"] + t["tree"]) + b["tree"] / (b["tree"] + b["bush"]))


def garden_matrix(ids: tuple[int, ...], wet: bool) -> np.ndarray:
    """Row-stochastic M[i, j] = P(given ids[j] | true ids[i]) over the garden's `ids` (the dry
    table's, or the wet one's with water), from the published rows by the mapping above. A class
    the mapping does not cover (unknown) is never confused."""
    index = {cid: k for k, cid in enumerate(ids)}
    swap = shrub_swap()
    m = np.zeros((len(ids), len(ids)))
    for cid, k in index.items():
        sources = TRUE_FROM.get(cid)
        if sources is None:
            m[k, k] = 1.0
            continue
        for name in sources:
            for predicted, share in RELLIS3D_HRNET_ROWS[name].items():
                share /= len(sources)
                if predicted == "sky":
                    continue
                if predicted == "bush":
                    if cid in SHRUBS:
                        for s in SHRUBS:
                            m[k, index[s]] += share * ((1 - 2 * swap) if s == cid else swap)
                    else:
                        for s in SHRUBS:
                            m[k, index[s]] += share / len(SHRUBS)
                    continue
                given = PREDICTED_AS[predicted]
                if given == WATER and not wet:
                    given = TERRAIN  # a puddle where the dry garden has no water: wet ground
                m[k, index[given]] += share
        m[k] /= m[k].sum()  # the dropped sky share, and the published rounding
    return m
