"""Measurement data sets: the format of ``shared/spec/dataset.md`` (see :mod:`comp_daemon.data.dataset`)."""
