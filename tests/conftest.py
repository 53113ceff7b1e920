"""Shared fixtures: paths to the shared specification, robots."""

from __future__ import annotations

import os

# One BLAS thread per test process: the suite runs beside the daemon's own threads on a 2-core
# machine, where multithreaded BLAS on small matrices is several times slower, not faster.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

from pathlib import Path  # noqa: E402

import pytest  # noqa: E402

SPEC_DIR = Path(__file__).resolve().parents[2] / "shared" / "spec"
FALLBACK_SPEC_DIR = Path(__file__).resolve().parent / "spec"


@pytest.fixture(scope="session")
def spec_dir() -> Path:
    """The shared specification folder (beside the checkout), or the copy kept in tests/spec."""
    for candidate in (SPEC_DIR, FALLBACK_SPEC_DIR):
        if (candidate / "kr210_fk_vectors.csv").is_file():
            return candidate
    pytest.fail("shared/spec/kr210_fk_vectors.csv not found beside the checkout nor in tests/spec")
