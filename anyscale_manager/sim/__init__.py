"""The simulated world that drives the same runtime core as the live decider, without ROS."""
