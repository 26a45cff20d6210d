"""The GPS/array error-state Kalman filter on filterpy, and its evaluation (errors, NEES/NIS).

Layer: imports the core (``ngnav``) only; neither the core nor ``telemetry`` imports it
(:mod:`ngnav.cli` and :mod:`ngnav.api` wire it in). Design: ``docs/design.md``.
"""
