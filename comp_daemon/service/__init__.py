"""The HTTP service of the daemon: configuration, persistence, API, jobs, metrics, live events, dashboard.

Modules: :mod:`~comp_daemon.service.config` (settings), :mod:`~comp_daemon.service.store` (SQLite),
:mod:`~comp_daemon.service.api` (``create_app``, ``open_store``), :mod:`~comp_daemon.service.jobs`
(process pool), :mod:`~comp_daemon.service.metrics` (Prometheus objects the loop updates),
:mod:`~comp_daemon.service.events` (the bus behind ``/api/events``), :mod:`~comp_daemon.common.logs`
(structlog), :mod:`~comp_daemon.service.daemon_view` (what the service may see of the daemon).
Nothing is imported here, so that the real-time code can import ``metrics`` without the web stack.
"""
