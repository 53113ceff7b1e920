"""Kinematics of six-axis arms, batch-first over n poses; the conventions are written once, in
:mod:`~comp_daemon.kinematics.params` (DH) and :mod:`~comp_daemon.kinematics.poe` (POE).

* :mod:`~comp_daemon.kinematics.params`: the kinematic parameters, the identification vector, axis ↔ DH;
* :mod:`~comp_daemon.kinematics.forward`: forward kinematics, Jacobians, gravity torques;
* :mod:`~comp_daemon.kinematics.inverse`: numerical inverse kinematics;
* :mod:`~comp_daemon.kinematics.poe`: the product-of-exponentials chain and its Δl/Δθ errors;
* :mod:`~comp_daemon.kinematics.so3`, :mod:`~comp_daemon.kinematics.kuka_abc`: rotations, KUKA A, B, C.

Import from the module that defines a name; the package re-exports nothing.
"""
