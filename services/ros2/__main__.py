"""`smana ros2`: smana as a ROS 2 node over rmw_zenoh (no ROS install, no bridge process).

Publishes /smana/<robot>/{map,costmap,path,goal,odom}, answers /smana/<robot>/plan
(nav_msgs/srv/GetPlan), serves the actions /smana/<robot>/navigate_to_pose and
/smana/<robot>/compute_path_to_pose (nav2_msgs) and takes /goal_pose as a goal; for a real
robot it also reads [ros2] cloud_topic, odom_topic and /tf_static and sends the explorer's
commands to cmd_vel_topic. ROS 2 nodes reach it through a zenoh router with gossip on: smana's
own (`smana up --set deploy.ros2.enabled=true`) or the robot's rmw_zenohd
(`--connect tcp/<robot>:7447`). See docs/ros2.md.
"""

from __future__ import annotations

import sys

from smana.common.cli import ServiceCommand, doc_summary, run_command

# a config that cannot work: one line, no traceback
COMMAND = ServiceCommand(
    "ros2", doc_summary(__doc__), "smana.services.ros2.service:main", (OSError, ValueError)
)


def cli(argv: list[str] | None = None) -> int:
    cfg = COMMAND.config(COMMAND.parser().parse_args(argv))
    try:
        import rosbags  # noqa: F401 - message types, CDR and type hashes
    except ImportError:
        print("smana ros2: needs the 'rosbags' package: pip install 'smana[ros2]'", file=sys.stderr)
        return 2
    return COMMAND.run(cfg)


if __name__ == "__main__":
    sys.exit(run_command("ros2", cli))
