"""Measurement data sets: the format of ``shared/spec/dataset.md`` (see :mod:`comp_daemon.data.dataset`),
and the ballbar and cross-bar campaign forms of ``shared/spec/seeds-002-003.md``
(:mod:`comp_daemon.data.ballbar`, :mod:`comp_daemon.data.crossbar`; either one read by
:func:`comp_daemon.data.campaigns.read_campaign`)."""
