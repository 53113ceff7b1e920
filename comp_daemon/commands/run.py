"""``comp-daemon run --config FILE [--sim]``: the real-time daemon with its HTTP service.

Runs until SIGTERM or SIGINT and exits 0 after a clean shutdown (corrections zeroed, state
persisted); 1 if one of its tasks failed; 2 for a configuration the user must fix; 3
(:data:`EXIT_STORE`) when the store cannot be used — damaged, missing or empty where a store
existed, on a full disk, or in use by another daemon — with one line that says what, where and what
to do (the unit in ``deploy/`` does not restart on 3: the operator must act first). Under systemd
(``Type=notify``) it reports readiness and sends watchdog pings (see ``deploy/``).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import os
import secrets
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from comp_daemon.sim_client import check_scenario, preset_scenarios

if TYPE_CHECKING:
    from comp_daemon.service.config import Settings


def register(subparsers: argparse._SubParsersAction) -> None:
    run = subparsers.add_parser(
        "run",
        help="run the daemon: RSI loop, grating readers, target queue, HTTP service",
        description="Run the real-time daemon (RSI loop and grating readers in a real-time process of "
        "their own, target executor, HTTP service) until SIGTERM/SIGINT.",
    )
    run.add_argument(
        "--config",
        metavar="FILE",
        help="configuration file (TOML; see config.example.toml). Optional with --sim: the quick start "
        "keeps its data in ./var/sim and makes an engineer token there",
    )
    run.add_argument(
        "--sim",
        action="store_true",
        help="bring up the simulated cell (robot, RSI controller, grating converters, tracker) in a "
        "child process and work against it",
    )
    run.add_argument(
        "--scenario",
        default="kr210-cell",
        help=f"with --sim: scenario preset ({', '.join(preset_scenarios())}) or TOML path "
        "(default kr210-cell)",
    )
    run.add_argument(
        "--sim-seed", type=int, default=0, help="with --sim: seed of the robot's noise (default 0)"
    )
    run.add_argument(
        "--servo-lag-cycles", type=int, default=1, help="with --sim: the controller's servo lag (default 1)"
    )
    run.add_argument(
        "--rearm-after-s",
        type=float,
        default=5.0,
        help="with --sim: the simulated controller restarts RSI this long after a stop, as an operator "
        "would (default 5; 0 or less: never)",
    )
    run.add_argument(
        "--motion",
        metavar="HOST:PORT",
        default=None,
        help="the cell gateway that takes motion commands (line protocol, docs/daemon.md); not with --sim",
    )
    run.add_argument(
        "--calibrate-gratings",
        action="store_true",
        help="run the grating calibration (seed 000 step 1) once the loop runs, before taking targets",
    )
    run.set_defaults(func=_run)


QUICK_START_TIMEOUT_COUNT = 100
#: the exit code for a store that cannot be used (``RestartPreventExitStatus=3`` in the unit)
EXIT_STORE = 3


def _quick_start_settings(data_dir: Path) -> Any:
    """Settings for ``run --sim`` without a file: data in ``data_dir``, one engineer token kept there."""
    from comp_daemon.service.config import load_settings

    data_dir.mkdir(parents=True, exist_ok=True)
    token_file = data_dir / "quickstart-token"
    if not token_file.exists():
        fd = os.open(token_file, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(secrets.token_urlsafe(24) + "\n")
    # the quick start runs on whatever machine it is tried on, often a busy laptop: its simulated
    # controller tolerates 100 late replies per RSI session instead of a cell's usual 10 (a real
    # cell's limit is in its configuration file, [rsi] timeout_count; docs/reliability.md measures both)
    return load_settings(
        None,
        rsi={"timeout_count": QUICK_START_TIMEOUT_COUNT},
        store={"data_dir": data_dir.resolve()},
        auth={"tokens": [{"name": "quickstart", "role": "engineer", "token_file": token_file.resolve()}]},
    )


def _address(text: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"--motion must be HOST:PORT, got {text!r}")
    return host.strip("[]"), int(port)


def _settings(args: argparse.Namespace) -> Settings:
    """The daemon's settings (``--config``, or the simulated cell's quick start, which then
    calibrates the gratings and prints where its dashboard is), checked, with the logging set up and
    the umask made private."""
    from pydantic import ValidationError

    from comp_daemon.common.logs import configure_logging
    from comp_daemon.rt.scheduling import check_cpus
    from comp_daemon.service.config import load_settings

    # everything the daemon and its children create (data folder, database with its -wal/-shm,
    # model artifacts, grating calibrations, spooled uploads) is private to its user, whatever the
    # umask it was started with; the umask only takes bits away, so a stricter one is kept
    os.umask(os.umask(0o077) | 0o077)
    try:
        settings = load_settings(args.config) if args.config else _quick_start_settings(Path("var/sim"))
    except ValidationError as exc:
        raise ValueError(f"{args.config or 'quick start'}: {exc}") from None
    check_cpus(settings.jobs.cpus, "jobs.cpus")
    if isinstance(settings.realtime.cpu, int):
        check_cpus([settings.realtime.cpu], "realtime.cpu")
    configure_logging(settings.log.level, settings.log.format)
    if args.config is None:
        args.calibrate_gratings = True  # the quick start's cell is ready without an engineer's step
        token = settings.auth.tokens[0].secret
        host = settings.http.host
        print(
            f"comp-daemon: simulated cell; data in {settings.store.data_dir.resolve()}; dashboard "
            f"http://{host}:{settings.http.port}/#token={token} (engineer token in "
            f"{settings.auth.tokens[0].token_file})",
            file=sys.stderr,
            flush=True,
        )
    return settings


def _run(args: argparse.Namespace) -> int:
    from comp_daemon.daemon.app import Daemon, SimOptions

    if args.sim and args.motion:
        raise ValueError("--motion and --sim exclude each other (the simulated cell has its own)")
    if args.config is None and not args.sim:
        raise ValueError("--config FILE is required (only the simulated cell, --sim, has a quick start)")
    if args.sim:
        check_scenario(args.scenario)
    settings = _settings(args)
    rearm = args.rearm_after_s if args.rearm_after_s > 0 else None
    sim = SimOptions(args.scenario, args.sim_seed, args.servo_lag_cycles, rearm) if args.sim else None
    motion = _address(args.motion) if args.motion else None
    daemon = Daemon(settings, sim=sim, motion_address=motion)

    async def main() -> int:
        calibration = None
        if args.calibrate_gratings:
            calibration = asyncio.get_running_loop().create_task(_calibrate_when_running(daemon))
        try:
            return await daemon.run()
        finally:
            if calibration is not None:
                calibration.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await calibration

    from comp_daemon.service.store import StoreError

    try:
        return asyncio.run(main())
    except StoreError as exc:
        print(f"comp-daemon run: cannot start: {exc}", file=sys.stderr, flush=True)
        return EXIT_STORE


async def _calibrate_when_running(daemon: object) -> None:
    from comp_daemon.common.logs import get_logger
    from comp_daemon.daemon.app import Daemon

    assert isinstance(daemon, Daemon)
    log = get_logger("comp_daemon.run")
    await daemon.started.wait()
    runtime = daemon.realtime.runtime
    for _ in range(600):  # up to 30 s for the first telegrams
        if runtime is not None and runtime.rsi_alive():
            break
        await asyncio.sleep(0.05)
    try:
        cal = await daemon.gratings.calibrate()
    except Exception as exc:
        log.error(f"grating calibration failed: {exc}")
        return
    log.info(f"grating calibration v{cal.version} stored and in use")
