"""A minimal service on the lifecycle base, for testing the base itself (tests/test_service.py).

- FIFO input `smana/<robot>/echo/pose` (Pose): counted in `poses` (frame_id "boom" raises, a
  stand-in for a handler's bug);
- latest-wins input `smana/<robot>/echo/cloud` (SemanticCloud): takes `--cloud-delay` seconds each;
- queryable `smana/<robot>/echo/count`: {"poses", "clouds", "points"};
- publisher `smana/<robot>/echo/out`: re-publishes each pose;
- `--warm-up S`: warm_up() takes S seconds (a stand-in for compiling kernels).
"""

from __future__ import annotations

import sys
import time

from smana.common import keys
from smana.common.cli import config_from_args, make_parser, setup_logging
from smana.common.messages import Pose, SemanticCloud
from smana.common.service import ReplyError, Service


class EchoService(Service):
    name = "echo"

    def __init__(self, config, cloud_delay_s: float, warm_up_s: float = 0.0):
        super().__init__(config)
        self.cloud_delay_s = cloud_delay_s
        self.warm_up_s = warm_up_s

    def warm_up(self):
        self.startup_step = "pretending to compile"
        self._stop.wait(self.warm_up_s)
        self.poses = self.clouds = self.points = 0

    def setup(self):
        self.out = self.publisher(keys.key(self.robot, "echo", "out"))
        self.subscribe(keys.key(self.robot, "echo", "pose"), self.on_pose, Pose)
        self.subscribe_latest(
            keys.key(self.robot, "echo", "cloud"), self.on_cloud, SemanticCloud, drop_nonfinite=True
        )
        self.queryable(keys.key(self.robot, "echo", "count"), self.on_count)

    def on_pose(self, pose: Pose):
        if pose.frame_id == "boom":
            raise RuntimeError("a handler bug, for the tests")
        self.poses += 1
        self.out.put(pose)

    def on_cloud(self, cloud: SemanticCloud):
        time.sleep(self.cloud_delay_s)  # simulated work: a slow handler
        self.clouds += 1
        self.points += len(cloud.points)
        if cloud.n_dropped_nonfinite:
            self.note("nonfinite_points", f"{cloud.n_dropped_nonfinite} NaN/inf points")

    def on_count(self, req):
        body = req.body()
        if body.get("fail"):
            raise ReplyError("refused", "asked to fail")
        return {"poses": self.poses, "clouds": self.clouds, "points": self.points}

    def status_details(self):
        return {"poses": self.poses}


def main(config, cloud_delay_s: float = 0.0, warm_up_s: float = 0.0) -> int:
    return EchoService(config, cloud_delay_s, warm_up_s).run()


def cli(argv: list[str] | None = None) -> int:
    p = make_parser("echo", __doc__)
    p.add_argument("--cloud-delay", type=float, default=0.0)
    p.add_argument("--warm-up", type=float, default=0.0, help="seconds warm_up() takes")
    args = p.parse_args(argv)
    cfg = config_from_args(args)
    setup_logging(cfg.general.log_level, "echo")
    return main(cfg, args.cloud_delay, args.warm_up)


if __name__ == "__main__":
    sys.exit(cli())
