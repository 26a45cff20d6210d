"""Kalman filtering for ngnav (GPS + nine-accelerometer array); built on filterpy.

Empty until the filter issue lands; ``ngnav`` core never imports this package.
"""
