"""smana as a ROS 2 node over rmw_zenoh: map, costmap, path, goal, odometry and a plan service
out; a ROS 2 robot's clouds and odometry in, velocity commands out. No ROS install needed."""
