"""The one preparation of a measurement campaign that every door shares.

``fit``, ``evaluate``, ``diagnose``, ``compensate`` and the HTTP fit and diagnosis jobs all call
:func:`~comp_daemon.preparation.campaign.prepare_campaign`: approach directions (the file's, or
inferred from the pose order with the assumption said), the fit / check split, the row floor, the
frame of the measurements (robot base or a tracker's, registered on the fit rows) and the targets
per pose.
"""
