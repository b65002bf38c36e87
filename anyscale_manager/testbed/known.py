"""Open defects of the ICAR test-bed: Δ violations the package's judge (runtime/delta.py) finds
there that the system does not prevent yet.

The e2e tests and the soak print each one they see, with its length, as a known open defect and
count it apart; a violation on any other connection fails them. An entry leaves this table when
the defect is fixed or its evidence did not survive: its connection is then judged like every
other (docs/testbed.md).
"""

from typing import Dict

KNOWN_OPEN: Dict[str, str] = {
    'odometer_odometry': 'the 40 Hz odometer (Δ 0) on the CPU-capped robot can miss by '
                         '0.03 s in the soak (seen in a CI run at 9877e8d); its misses in '
                         "throttles were the judge's lag, fixed in f10ab4a",
    'amcl_ekf': 'AMCL made active on the CPU-capped robot (after a cut, a move back) can run at '
                'about its 2 Hz minimum for seconds while AR starts beside it; on three scales '
                'once 2.56 s below with AMCL on the laptop, cause not found',
    'odometry_ekf': "a decider starting inside the CPU-capped robot's quota held odometry -> "
                    'EKF (Δ 0) below 5 Hz for 0.4 s once in 6 restarts',
    'ekf_navigation': 'EKF -> navigation (Δ 0, 2 Hz) past 0.6 s when a decider takeover, a '
                      "participant joining the domain and AR's activation saturate the robot's "
                      'quota at once',
}

__all__ = ['KNOWN_OPEN']
