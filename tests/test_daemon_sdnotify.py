"""sd_notify over a real AF_UNIX datagram socket (path and abstract), and the watchdog interval."""

from __future__ import annotations

import os
import socket
from pathlib import Path

from comp_daemon.daemon.sdnotify import Notifier, watchdog_interval_s


def test_messages_reach_a_path_socket(tmp_path: Path) -> None:
    path = tmp_path / "notify"
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as server:
        server.bind(str(path))
        n = Notifier({"NOTIFY_SOCKET": str(path)})
        assert n.enabled
        assert n.ready("loop running")
        assert n.watchdog()
        assert n.status("two\nlines")
        assert n.stopping()
        got = [server.recv(1024).decode() for _ in range(4)]
        n.close()
    assert got == ["READY=1\nSTATUS=loop running", "WATCHDOG=1", "STATUS=two lines", "STOPPING=1"]


def test_abstract_socket_and_no_socket() -> None:
    name = f"comp-daemon-test-{os.getpid()}"
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as server:
        server.bind("\0" + name)
        n = Notifier({"NOTIFY_SOCKET": "@" + name})
        assert n.watchdog()
        assert server.recv(64) == b"WATCHDOG=1"
        n.close()
    off = Notifier({})
    assert not off.enabled and not off.ready() and not off.watchdog()
    gone = Notifier({"NOTIFY_SOCKET": "/nonexistent/notify"})
    assert not gone.watchdog() and gone.errors == 1
    gone.close()


def test_watchdog_interval_is_half_the_setting() -> None:
    assert watchdog_interval_s({"WATCHDOG_USEC": "5000000"}) == 2.5
    assert watchdog_interval_s({}) is None
    assert watchdog_interval_s({"WATCHDOG_USEC": "junk"}) is None
    assert watchdog_interval_s({"WATCHDOG_USEC": "5000000", "WATCHDOG_PID": "1"}) is None  # not us
    assert watchdog_interval_s({"WATCHDOG_USEC": "5000000", "WATCHDOG_PID": str(os.getpid())}) == 2.5
