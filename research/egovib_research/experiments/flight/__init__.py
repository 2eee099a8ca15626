"""The package on a real recording: a quadcopter's gyro shaken by its own motors.

Data: Betaflight blackbox log ``LOG00037.BFL`` of a 5-inch FPV quadcopter ("AR8",
KakuteF7, Betaflight 4.2.0), from the public repository ``ilya-epifanov/fc-blackbox``
(file ``src/test-data/LOG00037.BFL``, licence MIT OR Apache-2.0; the log was first
posted in ``gyroflow/gyroflow`` issues/72), decoded with the ``orangebox`` parser.
Keep this attribution wherever the data or anything derived from it is shipped.

Modules:
    flightlog   the decoded log (npz) as arrays, validated
    convert     npz -> rosbag2 bag (``egovib real convert``), shipped at bags/quadcopter_ar8
    recording   the bag -> arrays (raw gyro, firmware-filtered gyro, motor commands)
    events      synthetic contact-like transients (the paper's experiment (b))
    notch       motor-speed-keyed harmonic notch bank (Betaflight RPM filter / ArduPilot
                harmonic notch), the map from motor command to line frequency
    methods     ours and the baselines a user would otherwise pick, on one footing
    experiment  calibrate on the first part of the flight, denoise the rest with events
                added (``egovib real evaluate``); report: table, JSON, figures
    cli         the ``egovib real`` commands
"""

ATTRIBUTION = (
    "Betaflight blackbox log LOG00037.BFL (quadcopter 'AR8', KakuteF7, Betaflight 4.2.0) from "
    "github.com/ilya-epifanov/fc-blackbox, src/test-data/LOG00037.BFL, licence MIT OR Apache-2.0; "
    "first posted in github.com/gyroflow/gyroflow/issues/72; decoded with the orangebox parser."
)
