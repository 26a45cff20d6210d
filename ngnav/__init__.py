"""ngnav: GPS-aided navigation with a gyro-free, nine-accelerometer IMU.

The core package has no I/O and imports neither ``filters`` nor ``telemetry``.
Conventions (frames, quaternions, units) are stated once in
:mod:`ngnav.conventions`.
"""

__version__ = "0.1.0"
