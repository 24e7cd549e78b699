"""TSDF surface extraction (zero crossing between face neighbours, a minimum weight) against a slow
reference over a dict of voxels, on random TSDF states and on a plane and a sphere integrated
from synthetic scans; and the MapDelta of a cloud carrying every voxel whose status may change."""

from __future__ import annotations

import numpy as np
import pytest

from smana.services.mapper.backends.tsdf import TsdfConfig
from smana.services.mapper.semantic_map import SemanticMap

# The surface rule on single rays: min_weight 1e-4 keeps a crossing one ray made (the default, 3,
# waits for about three rays: the pose-noise filter docs/experiments.md chose; tested below)
SEEN_ONCE = TsdfConfig(min_weight=1e-4)
FACES = [(1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1)]


def ref_surface(vox: dict[tuple, tuple[float, float]], min_weight: float) -> set[tuple]:
    """The rule written out: weight >= min_weight, a face neighbour of weight >= min_weight with
    the other sign, and this voxel nearer zero (on a tie, the one with d >= 0)."""
    out = set()
    for key, (d, w) in vox.items():
        if w < min_weight:
            continue
        for f in FACES:
            nb = vox.get((key[0] + f[0], key[1] + f[1], key[2] + f[2]))
            if nb is None or nb[1] < min_weight or (nb[0] < 0) == (d < 0):
                continue
            if abs(d) < abs(nb[0]) or (abs(d) == abs(nb[0]) and d >= 0):
                out.add(key)
                break
    return out


def voxel_dict(m: SemanticMap) -> dict[tuple, tuple[float, float]]:
    core = m._core
    g = core.observed_index()
    keys = core.grid.coords(g)
    c = core.grid.cols
    return {
        tuple(k): (float(d), float(w))
        for k, d, w in zip(keys.tolist(), c["distance"][g], c["weight"][g], strict=True)
    }


def surface_keys(m: SemanticMap) -> set[tuple]:
    core = m._core
    return {tuple(k) for k in core.grid.coords(core.occupied_index()).tolist()}


@pytest.mark.parametrize("seed", range(6))
def test_random_states_match_the_reference(seed):
    rng = np.random.default_rng(seed)
    min_weight = [1e-4, 0.5][seed % 2]
    m = SemanticMap("tsdf", 0.1, 10.0, config=TsdfConfig(min_weight=min_weight))
    core = m._core
    # a dense random cube crossing block borders (blocks of 8), with holes and tied distances
    keys = np.stack(np.meshgrid(*[np.arange(-6, 7)] * 3, indexing="ij"), -1).reshape(-1, 3)
    keys = keys[rng.random(len(keys)) < 0.8]
    g = core.grid.insert(keys)
    c = core.grid.cols
    c["distance"][g] = rng.choice([-0.2, -0.1, -0.05, 0.0, 0.05, 0.1, 0.2], len(g)) + (
        rng.random(len(g)) < 0.5
    ) * rng.normal(0, 0.03, len(g))
    c["weight"][g] = rng.choice([0.0, 1e-5, 0.3, 1.0, 5.0], len(g))
    c["flags"][g] = (c["weight"][g] > 0).astype(np.uint8)  # OBSERVED as the integrator sets it
    core.recount()
    expected = ref_surface(voxel_dict(m), min_weight)
    assert expected and surface_keys(m) == expected
    assert core.n_occupied == len(expected)
    rows = m.occupied_voxels()
    assert rows.occupied.all() and len(rows.keys) == len(expected)


def test_surface_checks_its_indices():
    m = SemanticMap("tsdf", 0.1, 10.0, config=SEEN_ONCE)
    with pytest.raises(ValueError, match="indices"):
        m._core.surface(np.array([0]))  # no block yet
    with pytest.raises(ValueError, match="1-D"):
        m._core.surface(np.zeros((1, 1), np.int64))


def plane_scan(x_m, half_m, step_m):
    s = np.arange(-half_m, half_m + 1e-9, step_m)
    yy, zz = np.meshgrid(s, s, indexing="ij")
    pts = np.stack([np.full(yy.size, x_m), yy.ravel(), zz.ravel()], -1)
    return pts.astype(np.float32)


def integrate_ray_by_ray(m, pts, label, origin):
    # One cloud per point: within a cloud the fast integrator drops the rest of a ray entering a
    # voxel another ray updated, which leaves unobserved voxels (holes) this test is not about.
    for p in pts:
        m.integrate(p[None], np.array([label]), None, origin)


def test_plane_surface_is_one_voxel_thick_at_the_plane():
    res, x_plane = 0.1, 2.03
    m = SemanticMap("tsdf", res, 10.0, config=SEEN_ONCE)
    rng = np.random.default_rng(0)
    for _ in range(2):  # scans from slightly different origins
        origin = tuple(rng.normal(0, 0.05, 3) + 0.05)
        pts = plane_scan(x_plane, 0.75, res) + np.array([0, 0.05, 0.05], np.float32)
        integrate_ray_by_ray(m, pts, 2, origin)
    surf = surface_keys(m)
    assert surf == ref_surface(voxel_dict(m), SEEN_ONCE.min_weight)
    cols: dict[tuple, list[int]] = {}
    for k in surf:
        cols.setdefault((k[1], k[2]), []).append(k[0])
    assert all(len(v) == 1 for v in cols.values())  # one voxel thick
    # the crossing lies in voxel 20 (1.95 m is 0.08 m in front, 2.05 m 0.02 m behind)
    assert {v[0] for v in cols.values()} == {20}
    inner = [(y, z) for y in range(-7, 7) for z in range(-7, 7)]
    assert all(c in cols for c in inner)  # and without holes inside the patch
    # the old rule (|d| < one voxel) made a two-voxel band
    old = {k for k, (d, w) in voxel_dict(m).items() if abs(d) < res and w > 0}
    assert len(old) > 1.8 * len(surf)


def test_sphere_surface_lies_on_the_sphere():
    res, radius = 0.1, 1.5
    m = SemanticMap("tsdf", res, 10.0, config=SEEN_ONCE)
    rng = np.random.default_rng(1)
    centre = np.array([0.05, 0.05, 0.05])
    u = rng.normal(size=(6000, 3))  # scanned from inside, near the centre (see the plane)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    pts = (centre + radius * u).astype(np.float32)
    integrate_ray_by_ray(m, pts, 4, tuple(centre + rng.normal(0, 0.02, 3)))
    surf = surface_keys(m)
    assert surf == ref_surface(voxel_dict(m), SEEN_ONCE.min_weight)
    centres = (np.array(sorted(surf)) + 0.5) * res
    r = np.linalg.norm(centres - centre, axis=1)
    # a voxel on the crossing has its centre within half a diagonal of the sphere
    assert np.abs(r - radius).max() <= res * np.sqrt(3) / 2 + 1e-6
    # One voxel per sign change, a voxel taking up to 3 of them where the surface runs diagonally:
    # about 0.83 voxels per res^2 of sphere here (0.78 with 6000 rays, 0.83 with 20000).
    area_vox = 4 * np.pi * radius**2 / res**2
    assert 0.7 * area_vox < len(surf) < 1.2 * area_vox
    old = {k for k, (d, w) in voxel_dict(m).items() if abs(d) < res and w > 0}
    assert len(surf) < 0.5 * len(old)  # the old band rule: 5328 voxels


def test_deltas_carry_every_voxel_whose_status_changed():
    """Applying each cloud's delta to a dict reproduces the extracted surface of the whole map,
    and the incremental count follows it."""
    res = 0.1
    m = SemanticMap("tsdf", res, 10.0, config=SEEN_ONCE)
    rng = np.random.default_rng(2)
    seen: dict[tuple, bool] = {}
    for i in range(8):
        # a plane that moves: its old surface voxels must leave the surface through the deltas
        pts = plane_scan(1.5 + 0.04 * i, 0.4, 0.03) + rng.normal(0, 0.01, (1, 3)).astype(np.float32)
        d = m.integrate(pts, np.full(len(pts), 2), None, (0.05, 0.05, 0.05))
        for k, occ in zip(d.keys.tolist(), d.occupied, strict=True):
            seen[tuple(k)] = bool(occ)
        assert {k for k, v in seen.items() if v} == surface_keys(m)
        assert m._core.n_occupied == len(surface_keys(m))


def test_a_loaded_map_without_surface_bits_keeps_its_count(tmp_path):
    """Format 2 files written before the extraction have no SURFACE bits: loading rebuilds them, so
    the incremental count stays right for the clouds that follow."""
    from smana.services.mapper.backends.tsdf import SURFACE

    m = SemanticMap("tsdf", 0.1, 10.0, config=SEEN_ONCE)
    pts = plane_scan(1.53, 0.4, 0.1) + np.array([0, 0.05, 0.05], np.float32)
    integrate_ray_by_ray(m, pts, 2, (0.05, 0.05, 0.05))
    m._core.grid.cols["flags"][:] &= ~SURFACE  # what an old file holds
    loaded = SemanticMap.load(m.save(tmp_path / "map.npz"))
    assert loaded._core.n_occupied == len(surface_keys(loaded)) == len(surface_keys(m)) > 0
    integrate_ray_by_ray(loaded, pts + np.float32(0.04), 2, (0.05, 0.05, 0.05))
    assert loaded._core.n_occupied == len(surface_keys(loaded))


def test_the_default_min_weight_waits_for_three_rays():
    """A crossing made by one ray is not surface under the default; the same ray three times is."""
    ray = (np.array([[2.03, 0.05, 0.05]], np.float32), np.array([2]), None, (0.05, 0.05, 0.05))
    assert TsdfConfig().min_weight == 3.0
    m = SemanticMap("tsdf", 0.1, 10.0)
    for n in (1, 2, 3):
        m.integrate(*ray)
        assert (len(surface_keys(m)) > 0) == (n >= 3), n
