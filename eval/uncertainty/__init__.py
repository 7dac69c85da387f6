"""Calibrating and checking the error bars of ``--uncertainty`` (``capssim bench uncertainty``): split conformal
calibration on simulated development captures, and the coverage on development captures it did not see."""
