"""Measurement data sets: the format of ``docs/data-format.md`` (see :mod:`comp_daemon.data.dataset`),
and the ballbar and cross-bar campaign forms of ``docs/data-format.md``
(:mod:`comp_daemon.data.ballbar`, :mod:`comp_daemon.data.crossbar`; either one read by
:func:`comp_daemon.data.campaigns.read_campaign`)."""
