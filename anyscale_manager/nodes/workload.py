"""The workload node (entry point `ros2 run anyscale_manager workload`); built in its own issue."""

import sys


def main(args=None) -> int:
    print('anyscale_manager workload: not yet implemented', file=sys.stderr)
    return 2


if __name__ == '__main__':
    sys.exit(main())
