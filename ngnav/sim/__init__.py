"""Simulation: flight and turntable truth, sensor and GPS models, scenarios, ``simulate_flight``.

Nothing here is needed to filter a recorded run.
"""
