"""How many threads the numeric libraries (OpenBLAS, MKL, OpenMP) may use, set on purpose.

NumPy's BLAS starts as many threads as the machine has cores. The numerics here work on small
matrices (a few hundred rows × tens of parameters) where those threads gain little alone, and cost
a great deal beside other numeric work: several processes each with a thread per core spin against
each other (three diagnoses side by side took 4.5× the CPU of one alone; a job worker pinned to one
core with two BLAS threads, 4× the wall time of the command line). The command line, every job
worker of the daemon and the benchmarks therefore set the count themselves, to
:data:`DEFAULT_THREADS` unless told otherwise, and run independent work in processes instead
(``evaluate --jobs``).

:func:`set_numeric_threads` sets it twice: in the environment variables the libraries read when
they load (so it holds for libraries not loaded yet and for child processes), and through
threadpoolctl for those already loaded.
"""

from __future__ import annotations

import os
from collections.abc import Sequence

__all__ = [
    "DEFAULT_THREADS",
    "THREADS_ENV",
    "THREAD_VARIABLES",
    "default_threads",
    "numeric_threads",
    "parse_threads",
    "set_numeric_threads",
    "threads_from_argv",
]

#: threads per process for the numeric libraries, unless ``--threads`` or ``COMP_DAEMON_THREADS``
#: says otherwise: one, since work runs in processes side by side (module docstring)
DEFAULT_THREADS = 1
#: the environment variable that sets the default of ``--threads``
THREADS_ENV = "COMP_DAEMON_THREADS"
#: the variables the numeric libraries read when they load
THREAD_VARIABLES = (
    "OMP_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
    "MKL_NUM_THREADS",
    "BLIS_NUM_THREADS",
    "VECLIB_MAXIMUM_THREADS",
    "NUMEXPR_NUM_THREADS",
)
MAX_THREADS = 256  # the most a count may ask for


def parse_threads(text: str, what: str = "--threads") -> int:
    """A thread count 1..256 from ``text``, or a ValueError naming ``what``."""
    value = text.strip()
    if not value.isdigit() or not 1 <= int(value) <= MAX_THREADS:
        raise ValueError(f"{what}: expected a thread count 1..{MAX_THREADS}, got {text!r}")
    return int(value)


def default_threads() -> int:
    """``COMP_DAEMON_THREADS`` when set, else :data:`DEFAULT_THREADS`."""
    text = os.environ.get(THREADS_ENV)
    return DEFAULT_THREADS if text is None or not text.strip() else parse_threads(text, THREADS_ENV)


def threads_from_argv(argv: Sequence[str]) -> int:
    """The thread count a command line asks for: its ``--threads N`` / ``--threads=N`` before the
    first word that is not an option, else :func:`default_threads`. Read before NumPy loads."""
    words = list(argv)
    for i, word in enumerate(words):
        if word == "--threads":
            if i + 1 >= len(words):
                raise ValueError("--threads: expected a thread count after it")
            return parse_threads(words[i + 1])
        if word.startswith("--threads="):
            return parse_threads(word.partition("=")[2])
        if not word.startswith("-"):
            break
    return default_threads()


def set_numeric_threads(threads: int) -> None:
    """Let the numeric libraries use ``threads`` threads in this process and its children
    (module docstring)."""
    if not 1 <= threads <= MAX_THREADS:
        raise ValueError(f"expected a thread count 1..{MAX_THREADS}, got {threads}")
    for name in THREAD_VARIABLES:
        os.environ[name] = str(threads)
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=threads)


def numeric_threads() -> dict[str, int]:
    """The thread count of each numeric library loaded in this process (for benchmarks and tests)."""
    from threadpoolctl import threadpool_info

    return {
        f"{info['internal_api']}:{info['user_api']}": int(info["num_threads"]) for info in threadpool_info()
    }
