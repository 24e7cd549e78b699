"""The ROS 2 action types smana serves, written as rosbags' typestore takes them (no network at
run time): nav2_msgs' NavigateToPose and ComputePathToPose (ROS 2 Jazzy, navigation2's `jazzy`
branch, `nav2_msgs/action/*.action`) and action_msgs' CancelGoal service (rcl_interfaces'
`jazzy` branch; GoalInfo, GoalStatus and GoalStatusArray are already in rosbags' Jazzy store).

An action `pkg/action/A` is, on the wire, three services and two topics (rosidl_parser's
`Action`, as rcl_action names them under `<action name>/_action/`):

- `send_goal`   service `pkg/action/A_SendGoal`:  {UUID goal_id, A_Goal goal} ->
                {bool accepted, builtin_interfaces/Time stamp}
- `get_result`  service `pkg/action/A_GetResult`: {UUID goal_id} -> {int8 status, A_Result result}
- `cancel_goal` service `action_msgs/srv/CancelGoal`
- `feedback`    topic `pkg/action/A_FeedbackMessage`: {UUID goal_id, A_Feedback feedback}
- `status`      topic `action_msgs/msg/GoalStatusArray`

Each service also has its `_Event` message (rosidl adds one to every service since Iron); the
service's RIHS01 hash covers request, response and event, as `rmw._service_types` writes them.
"""

from __future__ import annotations

# A message without fields gets this one from rosidl (and hashes with it).
_EMPTY = "uint8 structure_needs_at_least_one_member"

# (goal, result, feedback) as the .action files give them, comments left out.
ACTIONS = {
    "nav2_msgs/action/NavigateToPose": (
        "geometry_msgs/PoseStamped pose\nstring behavior_tree",
        "uint16 NONE=0\nuint16 error_code\nstring error_msg",
        "geometry_msgs/PoseStamped current_pose\n"
        "builtin_interfaces/Duration navigation_time\n"
        "builtin_interfaces/Duration estimated_time_remaining\n"
        "int16 number_of_recoveries\n"
        "float32 distance_remaining",
    ),
    "nav2_msgs/action/ComputePathToPose": (
        "geometry_msgs/PoseStamped goal\ngeometry_msgs/PoseStamped start\n"
        "string planner_id\nbool use_start",
        "uint16 NONE=0\nuint16 UNKNOWN=200\nuint16 INVALID_PLANNER=201\nuint16 TF_ERROR=202\n"
        "uint16 START_OUTSIDE_MAP=203\nuint16 GOAL_OUTSIDE_MAP=204\n"
        "uint16 START_OCCUPIED=205\nuint16 GOAL_OCCUPIED=206\nuint16 TIMEOUT=207\n"
        "uint16 NO_VALID_PATH=208\n"
        "nav_msgs/Path path\nbuiltin_interfaces/Duration planning_time\n"
        "uint16 error_code\nstring error_msg",
        "",
    ),
}

CANCEL_GOAL = "action_msgs/srv/CancelGoal"
CANCEL_GOAL_SRV = (
    "action_msgs/GoalInfo goal_info",
    "int8 ERROR_NONE=0\nint8 ERROR_REJECTED=1\nint8 ERROR_UNKNOWN_GOAL_ID=2\n"
    "int8 ERROR_GOAL_TERMINATED=3\n"
    "int8 return_code\naction_msgs/GoalInfo[] goals_canceling",
)
STATUS_ARRAY = "action_msgs/msg/GoalStatusArray"

# action_msgs/msg/GoalStatus
STATUS_UNKNOWN, STATUS_ACCEPTED, STATUS_EXECUTING, STATUS_CANCELING = 0, 1, 2, 3
STATUS_SUCCEEDED, STATUS_CANCELED, STATUS_ABORTED = 4, 5, 6
TERMINAL = (STATUS_SUCCEEDED, STATUS_CANCELED, STATUS_ABORTED)
# action_msgs/srv/CancelGoal_Response
CANCEL_NONE, CANCEL_REJECTED, CANCEL_UNKNOWN_GOAL_ID, CANCEL_GOAL_TERMINATED = 0, 1, 2, 3


def part(action: str, what: str) -> str:
    """`part("nav2_msgs/action/NavigateToPose", "SendGoal")` -> its implicit type's name."""
    return f"{action}_{what}"


def service_parts(action: str) -> dict[str, tuple[str, str]]:
    """The action's two services as (request, response) definitions."""
    uuid = "unique_identifier_msgs/UUID goal_id"
    name = action.rsplit("/", 1)[1]
    return {
        part(action, "SendGoal"): (
            f"{uuid}\n{name}_Goal goal",
            "bool accepted\nbuiltin_interfaces/Time stamp",
        ),
        part(action, "GetResult"): (uuid, f"int8 status\n{name}_Result result"),
    }


def register(store, service_types, actions: dict | None = None) -> None:
    """Add the action types to a rosbags typestore; `service_types(name, request, response)` is
    `rmw._service_types` (one writer of a service's request, response and event); `actions`
    (default ACTIONS) as {name: (goal, result, feedback)}."""
    from rosbags.typesys import get_types_from_msg

    actions = ACTIONS if actions is None else actions
    found: dict = {}
    for action, (goal, result, feedback) in actions.items():
        name = action.rsplit("/", 1)[1]
        for suffix, text in (("Goal", goal), ("Result", result), ("Feedback", feedback)):
            found.update(get_types_from_msg(text or _EMPTY, part(action, suffix)))
        found.update(
            get_types_from_msg(
                f"unique_identifier_msgs/UUID goal_id\n{name}_Feedback feedback",
                part(action, "FeedbackMessage"),
            )
        )
    store.register(found)
    for action in actions:
        for srv, (request, response) in service_parts(action).items():
            store.register(service_types(srv, request, response))
    if CANCEL_GOAL + "_Request" not in store.fielddefs:
        store.register(service_types(CANCEL_GOAL, *CANCEL_GOAL_SRV))


def action_names(action: str) -> dict[str, str]:
    """{endpoint: type} of an action under `<name>/_action/`."""
    return {
        "send_goal": part(action, "SendGoal"),
        "get_result": part(action, "GetResult"),
        "cancel_goal": CANCEL_GOAL,
        "feedback": part(action, "FeedbackMessage"),
        "status": STATUS_ARRAY,
    }
