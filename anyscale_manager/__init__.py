"""anyscale_manager: run-time placement and migration of ROS 2 nodes across scales."""

__version__ = '0.1.0'
