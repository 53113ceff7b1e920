"""Models in the controller's own form: parameter listings and compensated target lists.

* :mod:`~comp_daemon.export.params`: a kinematic model's identified parameters as KUKA
  (KRL data list), ABB (``MOC.cfg``-like) and CSV listings, and their readers;
* :mod:`~comp_daemon.export.targets`: compensated targets as KRL (``E6AXIS`` / ``E6POS``),
  RAPID (``jointtarget`` / ``robtarget``) and CSV lists, and their readers;
* :mod:`~comp_daemon.export.frames`: the rotations and number texts they share.

Text in, values out: no file is read or written here (``comp-daemon export`` does that).
"""
