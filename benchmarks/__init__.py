"""The benchmarks: each sets the numeric libraries' threads on purpose before it loads NumPy (one,
or ``COMP_DAEMON_THREADS``), as the command line and the daemon's job workers do, so that their
figures do not depend on the shell they were started from (:mod:`comp_daemon.common.threads`)."""

from comp_daemon.common.threads import default_threads, set_numeric_threads

set_numeric_threads(default_threads())
