"""ngnav: GPS-aided navigation with a gyro-free, nine-accelerometer IMU; the core layer.

The array's physics, calibration, GM(1,1) compensation, flight and sensor simulation, run
files and the records passed between layers. Layers: core <- ``filters``, ``telemetry``, and
``telemetry`` never imports ``filters``; the core's two composition roots, :mod:`ngnav.cli` and
:mod:`ngnav.api`, are the only modules that import and wire the three. Conventions (frames,
quaternions, units) are stated once in :mod:`ngnav.conventions`.
"""

__version__ = "0.1.0"
