"""nav2_msgs' costmap messages, as Nav2's `nav2_msgs/msg/*.msg` sources define them (Jazzy; the
fields and their order are what the RIHS01 hash and the CDR see, the comments are left out).
rosbags' typestore has no nav2_msgs: `register` adds them to a store, from these texts, with no
network at run time."""

from __future__ import annotations

COSTMAP = "nav2_msgs/msg/Costmap"
COSTMAP_META = "nav2_msgs/msg/CostmapMetaData"

# nav2_msgs/msg/CostmapMetaData.msg
COSTMAP_META_MSG = """\
builtin_interfaces/Time map_load_time
builtin_interfaces/Time update_time
string layer
float32 resolution
uint32 size_x
uint32 size_y
geometry_msgs/Pose origin
"""

# nav2_msgs/msg/Costmap.msg: `data` is row-major from cell (0, 0), x fastest.
COSTMAP_MSG = """\
std_msgs/Header header
CostmapMetaData metadata
uint8[] data
"""

DEFINITIONS = {COSTMAP_META: COSTMAP_META_MSG, COSTMAP: COSTMAP_MSG}

# nav2_costmap_2d/cost_values.hpp
NO_INFORMATION = 255
LETHAL_OBSTACLE = 254
INSCRIBED_INFLATED_OBSTACLE = 253
MAX_NON_OBSTACLE = 252
FREE_SPACE = 0


def register(store) -> None:
    """Add the costmap types to a rosbags typestore (a relative field type such as
    `CostmapMetaData` resolves in its own package, as rosidl resolves it)."""
    from rosbags.typesys import get_types_from_msg

    types: dict = {}
    for name, text in DEFINITIONS.items():
        types.update(get_types_from_msg(text, name))
    store.register(types)
