"""Publish labelled clouds of a flat terrain patch with an obstacle block, as a sensor would.

    publish_clouds.py ENDPOINT FIRST COUNT [--user U --credentials FILE]

Cloud i covers the 2 m x 2 m patch whose corner is at x = 2*i, y = 0 (terrain, label 2) with a
0.4 m block of label 7 (obstacle) in its middle, seen from 1 m above the patch centre.
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np
import zenoh

from smana.common import keys
from smana.common.config import ZenohConfig
from smana.common.messages import MapDelta, MessageError, SemanticCloud, decode, encode
from smana.common.zenoh_config import make_zenoh_config


def patch_cloud(i: int, seq: int) -> SemanticCloud:
    g = np.arange(0.025, 2.0, 0.05)
    xx, yy = np.meshgrid(g, g)
    ground = np.column_stack([xx.ravel() + 2.0 * i, yy.ravel(), np.zeros(xx.size)])
    b = np.arange(0.825, 1.2, 0.05)
    bx, by, bz = np.meshgrid(b, b, np.arange(0.05, 0.5, 0.05))
    block = np.column_stack([bx.ravel() + 2.0 * i, by.ravel(), bz.ravel()])
    pts = np.vstack([ground, block]).astype(np.float32)
    labels = np.r_[np.full(len(ground), 2), np.full(len(block), 7)].astype(np.uint8)
    return SemanticCloud(
        stamp_s=time.time(),
        seq=seq,
        points=pts,
        labels=labels,
        confidences=np.full(len(pts), 0.9, np.float32),
        sensor_position=np.array([2.0 * i + 1.0, 1.0, 1.5]),
    )


def main() -> int:
    p = argparse.ArgumentParser()
    p.add_argument("endpoint")
    p.add_argument("first", type=int)
    p.add_argument("count", type=int)
    p.add_argument("--robot", default="r1")
    p.add_argument("--user", default="")
    p.add_argument("--credentials", default="")
    args = p.parse_args()
    zc = ZenohConfig(connect=[args.endpoint], user=args.user, credentials_file=args.credentials)
    with zenoh.open(make_zenoh_config(zc)) as session:
        mapped = MappedClouds()
        sub = session.declare_subscriber(keys.map_delta(args.robot), mapped.on_delta)
        pub = session.declare_publisher(keys.cloud(args.robot))
        if not wait(lambda: pub.matching_status.matching, TIMEOUT_S):
            print(f"no mapper subscribes to {keys.cloud(args.robot)}", file=sys.stderr)
            return 1
        # The mapper keeps the latest cloud only: each cloud goes once the one before it is
        # mapped (its delta is out), and the last one is mapped before the session closes.
        for i in range(args.first, args.first + args.count):
            pub.put(encode(patch_cloud(i, i + 1)))
            if not wait(lambda seq=i + 1: seq in mapped.seqs, TIMEOUT_S):
                print(f"cloud {i + 1} was not mapped in {TIMEOUT_S} s", file=sys.stderr)
                return 1
        sub.undeclare()
    return 0


TIMEOUT_S = 30.0


class MappedClouds:
    """The cloud numbers of the mapper's deltas: a subscriber declared before the first cloud is
    sent reaches the mapper before that cloud does (one link, in order)."""

    def __init__(self):
        self.seqs: set[int] = set()

    def on_delta(self, sample) -> None:
        try:
            self.seqs.add(decode(sample.payload.to_bytes(), MapDelta).cloud_seq)
        except MessageError:
            pass


def wait(pred, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while not pred():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.02)
    return True


if __name__ == "__main__":
    sys.exit(main())
