"""``anyscale-manager profile``: watch a running ROS 2 graph and write a deployment skeleton.

Pure parts (no rclpy): ``stats`` (rate readings, CPU readings), ``suggest`` (the threshold
rule), ``graph`` (what was seen, filtered), ``processes`` (node -> process), ``skeleton`` (the
YAML). The rclpy and psutil side is ``watch``; the command is ``cli``. See docs/profile.md.
"""
