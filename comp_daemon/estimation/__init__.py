"""Solvers and statistics of identification: least squares, optimisers, registration,
identifiability, kriging solvers, variograms, out-of-fold selection, measurement uncertainty.

Imported by the model kinds; imports none of them (only kinematics, robot, data, common).
"""
