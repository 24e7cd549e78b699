"""Lockstep replay into the real mapper service (both in-process on the fake zenoh,
tests/support/fake_zenoh.py) gives the same map as integrating the same scans with the core: no
scan lost, none integrated twice, nothing altered on the way."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from smana.common.classes import ClassTable
from smana.common.config import SmanaConfig
from smana.lab.data import synthetic as syn
from smana.services.replay.prepare import prepare_scan
from smana.services.replay.readers import open_dataset

mapper_takeover = pytest.importorskip("smana.services.mapper.takeover")
from smana.services.mapper.semantic_map import SemanticMap  # noqa: E402

N_SCANS = 5


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("synthetic")
    params = syn.SyntheticConfig(n_scans=N_SCANS, beams=16, columns=512, seed=1, noise_m=0.01)
    syn.write_rellis_sequence(root, params)
    return root


def sorted_rows(d):
    order = np.lexsort(d.centres.T[::-1])
    return d.subset(order)


@pytest.mark.parametrize("backend", ["octree-max", "tsdf"])
def test_lockstep_replay_builds_the_in_process_map(fake_stack, dataset, backend):
    zenoh_stack = fake_stack
    settings = [
        "general.class_table=rellis3d",
        'mapper.inputs=["scan"]',
        f"mapper.backend={backend}",
        "mapper.resolution_m=0.2",
        "mapper.autosave_period_s=0",
    ]
    sets = [a for s in settings for a in ("--set", s)]
    run = zenoh_stack.tmp / "mapper_run"
    mapper = zenoh_stack.service("mapper", "--run-dir", str(run), *sets)
    zenoh_stack.wait_alive("mapper")
    replay = zenoh_stack.service("replay", str(dataset), "--lockstep", *sets)
    assert replay.wait(timeout=120) == 0, zenoh_stack.log("replay")
    assert zenoh_stack.stop(mapper) == 0, zenoh_stack.log("mapper")
    served = SemanticMap.load(run / "map.npz", "rellis3d")

    cfg = SmanaConfig.load(None, settings)
    cfg = dataclasses.replace(cfg, general=dataclasses.replace(cfg.general, run_dir=""))
    table = ClassTable.load("rellis3d")
    local = mapper_takeover.build_map(cfg, table)
    with open_dataset(dataset) as reader:
        for scan in reader:
            pc = prepare_scan(scan, table, cfg.replay.max_range_m, cfg.replay.min_range_m)
            local.integrate(pc.points, pc.labels, pc.confidences, pc.sensor_position)

    assert served.n_integrations == local.n_integrations == N_SCANS
    assert served.stats()["voxels_observed"] == local.stats()["voxels_observed"]
    a, b = sorted_rows(served.occupied_voxels()), sorted_rows(local.occupied_voxels())
    # 5 sparse scans: a TSDF surface needs about 3 rays (mapper.tsdf.min_weight), so it keeps
    # fewer voxels than the octrees (383 against 500+)
    assert len(a) > 300
    np.testing.assert_array_equal(a.keys, b.keys)
    np.testing.assert_array_equal(a.labels, b.labels)
    np.testing.assert_array_equal(a.values, b.values)
    np.testing.assert_array_equal(a.confidences, b.confidences)
