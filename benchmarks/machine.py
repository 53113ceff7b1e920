"""Machine description printed with every benchmark result."""

from __future__ import annotations

import os
import platform

import numpy as np


def machine_info() -> dict[str, str | int | None]:
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "os": f"{platform.system()} {platform.release()}",
    }


def machine_line() -> str:
    m = machine_info()
    return f"{m['cpu']}, {m['cores']} cores, Python {m['python']}, NumPy {m['numpy']}, {m['os']}"
