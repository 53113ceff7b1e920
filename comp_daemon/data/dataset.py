"""The measurement data set (``docs/data-format.md``): one import for the type, readers and writer.

The :class:`Dataset` and its writer live in :mod:`comp_daemon.data.table` (units and equality are
described there); the CSV and JSON readers and their refusal rules in
:mod:`comp_daemon.data.readers`; column names and :class:`DatasetError` in
:mod:`comp_daemon.data.columns`.
"""

from __future__ import annotations

from comp_daemon.data.columns import DatasetError
from comp_daemon.data.readers import (
    DatasetKind,
    dataset_from_json,
    dataset_from_records,
    parse_dataset,
    read_dataset,
    read_dataset_file,
    read_dataset_json,
)
from comp_daemon.data.table import (
    DEFAULT_CHECK_FRACTION,
    DEFAULT_SPLIT_SEED,
    Dataset,
    SplitChoice,
    dataset_to_csv,
    write_dataset,
)

__all__ = [
    "DEFAULT_CHECK_FRACTION",
    "DEFAULT_SPLIT_SEED",
    "Dataset",
    "DatasetError",
    "DatasetKind",
    "SplitChoice",
    "dataset_from_json",
    "dataset_from_records",
    "dataset_to_csv",
    "parse_dataset",
    "read_dataset",
    "read_dataset_file",
    "read_dataset_json",
    "write_dataset",
]
