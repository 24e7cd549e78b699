"""`smana bench ros2-throughput` in its 20 s form: a 131,072-point PointCloud2 at 10 Hz from
zenoh-ros2-sdk across a router process into smana's rmw_zenoh subscription, with congestion
control BLOCK, arrives whole (sent = received, nothing dropped, every cloud decoded), and smana's
map goes out and is decoded by the SDK, bounded by the voxel budget."""

from __future__ import annotations

import argparse

import pytest

pytest.importorskip("zenoh_ros2_sdk")
pytest.importorskip("rosbags")

pytestmark = pytest.mark.multiprocess


def test_eight_seconds_of_131k_point_clouds_arrive_whole(tmp_path):
    # 8 s: 80 clouds and 8 maps (20 s, the bench's default, cost the suite 12 s more)
    from smana.lab.bench import ros2_throughput

    args = argparse.Namespace(
        duration=8.0,
        points=131_072,
        rate_hz=10.0,
        map_voxels=300_000,
        map_max_points=200_000,
        cloud_congestion="block",
    )
    r = ros2_throughput.run(args, tmp_path)
    c, m = r["clouds"], r["map"]
    assert c["sent"] > 0 and c["received"] == c["sent"], r
    assert c["dropped"] == 0 and c["undecodable"] == 0 and c["missing"] == [], r
    assert c["p50_ms"] is not None and c["p50_ms"] <= c["p99_ms"] <= c["max_ms"]
    assert r["cloud_bytes"] == 131_072 * 16
    # The map: over its budget, so coarsened to fit; what went out arrived or is counted dropped.
    assert 0 < m["points"] <= 200_000 and m["payload_bytes"] <= 20 * 200_000 + 1000
    assert m["received"] >= 1 and m["received"] + m["dropped"] == m["sent"], r
    assert (tmp_path / "result.json").exists()
