"""Calibration instruments other than the tracker: ballbar and cross-bar (their identification,
plans, campaign fits and the solver comparison of seed 002).
"""
