"""structlog records reach the standard library's handlers even before configure_logging runs."""

from __future__ import annotations

import logging

import pytest
import structlog

from comp_daemon.common.logs import get_logger


def test_records_before_configuration_are_plain_stdlib_lines(caplog: pytest.LogCaptureFixture) -> None:
    structlog.reset_defaults()
    caplog.set_level(logging.INFO)
    get_logger("comp_daemon.test").info("target 7 failed: feedback_stale", target_id=7, state="failed")
    record = next(r for r in caplog.records if r.name == "comp_daemon.test")
    assert record.levelno == logging.INFO
    assert record.getMessage() == "target 7 failed: feedback_stale target_id=7 state=failed"
    get_logger("comp_daemon.test").debug("not shown")
    assert not any("not shown" in r.getMessage() for r in caplog.records)
