"""A stand-in sensor for the recorder's stop test: a service that, once the recorder is alive,
publishes a Pose on `robot/pose` every tick (reliably, so none is lost on the way) until it is
stopped, and 20 more while it stops, then writes how many it published to
`<run_dir>/pose_source.json`."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from smana.common import keys
from smana.common.cli import config_from_args, make_parser, setup_logging
from smana.common.messages import Pose
from smana.common.service import Service


class PoseSource(Service):
    name = "sim"  # it stands in for the simulator
    tick_period_s = 0.005

    def __init__(self, config):
        super().__init__(config)
        self.published = 0
        self.recorder_alive = False

    def setup(self):
        self.pub = self.publisher(keys.pose(self.robot), reliable_block=True)
        self._declared.append(
            self.session.liveliness().declare_subscriber(
                keys.alive(self.robot, "recorder"), self._on_alive, history=True
            )
        )

    def _on_alive(self, sample):
        self.recorder_alive = True  # a zenoh thread: only a flag

    def tick(self):
        if self.recorder_alive:
            self._put()

    def _put(self):
        i = self.published
        self.pub.put(Pose.from_xyz_yaw(0.01 * i, 0.0, 0.0, 0.0, stamp_s=1.0 + 0.005 * i))
        self.published += 1

    def on_stop(self):
        # The last words of a stopping service (the explorer's final state, a driver's buffer):
        # sent while the stack stops, they are still to be recorded.
        for _ in range(20 if self.recorder_alive else 0):
            self._put()
        run_dir = Path(self.config.general.run_dir)
        (run_dir / "pose_source.json").write_text(json.dumps({"published": self.published}))


def cli(argv=None) -> int:
    args = make_parser("pose_source", "publish poses until stopped").parse_args(argv)
    cfg = config_from_args(args)
    setup_logging(cfg.general.log_level, "sim")
    return PoseSource(cfg).run()


if __name__ == "__main__":
    sys.exit(cli())
