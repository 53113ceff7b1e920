"""An upload checked in a process of its own (a spooled body) is refused with the reader's fields."""

from __future__ import annotations

import json

import pytest

from comp_daemon.robot.description import load_robot
from comp_daemon.service.uploads import Spool, UploadChecker, UploadRefused

RECORD = {"a1": 0.0, "a2": -90.0, "a3": 90.0, "a4": 0.0, "a5": 45.0, "a6": 0.0, "x": 1.0, "y": 2.0, "z": 3.0}


@pytest.mark.parametrize(
    ("last", "where"),
    [
        (
            json.dumps(RECORD)[:-1] + ', "z": 4}',
            {"path": "$.records[20000].z", "row": 20001, "column": "z", "row_label": "record"},
        ),
        (
            json.dumps({**RECORD, "note": "\\ud800"}).replace("\\\\", "\\"),
            {"path": "$.records[20000].note", "row": 20001, "column": "note", "row_label": "record"},
        ),
        (
            json.dumps({**RECORD, "a2": 10.0}),
            {"path": "$.records[20000].a2", "row": 20001, "column": "a2", "row_label": "record"},
        ),
    ],
    ids=["duplicate-key", "lone-surrogate", "outside-limits"],
)
async def test_a_spooled_json_upload_is_refused_with_path_row_and_column(last: str, where: dict) -> None:
    body = (
        '{"name": "big", "records": [' + ", ".join([json.dumps(RECORD)] * 20000) + ", " + last + "]}"
    ).encode()
    checker, spool = UploadChecker(1, 40_000_000), Spool()
    try:
        await spool.write(body)
        assert not spool.in_memory  # checked in a process of its own
        with pytest.raises(UploadRefused) as caught:
            await checker.check(
                spool, "json", "upload.json", load_robot("kr210").axis_limits_deg, "measurement"
            )
    finally:
        spool.close()
        checker.shutdown()
    assert caught.value.where == where
    assert f", {where['path']}, record 20001, column '{where['column']}': " in caught.value.message
