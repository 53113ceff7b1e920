"""Configuration of the daemon: one TOML file plus environment overrides.

``load_settings(path)`` reads the file (see ``config.example.toml``, which documents every
setting), then applies environment variables ``COMP_DAEMON_<SECTION>__<FIELD>`` (for example
``COMP_DAEMON_HTTP__PORT=9000``; lists and tables as JSON, e.g.
``COMP_DAEMON_RSI__CONTROLLER_ALLOW='["10.0.0.5"]'``). Precedence: explicit keyword arguments >
environment > file > defaults.

Units are in the field names (``_ms``, ``_s``, ``_deg``, ``_mm``, ``_nm``, ``_bytes``); every timeout
and limit is a named setting. Relative paths given in the file (``store.data_dir``,
``auth.tokens[].token_file``, ``robot.name`` when it is a path) are relative to the folder of the
file; without a file, to the working directory. Unknown keys are refused by name.
"""

from __future__ import annotations

import contextvars
import ipaddress
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from enum import IntEnum
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, SecretStr, field_validator, model_validator
from pydantic_settings import (
    BaseSettings,
    PydanticBaseSettingsSource,
    SettingsConfigDict,
    TomlConfigSettingsSource,
)

from comp_daemon.models.compensation import (
    DEFAULT_LIMITS,
    RENAMED_MAPPINGS,
    CompensationLimits,
    JointMapping,
    renamed_mapping_note,
)

__all__ = [
    "REMOVED_REALTIME_KEYS",
    "AuthSettings",
    "CompensationSettings",
    "ControllerSettings",
    "EncoderJointSettings",
    "EncoderSettings",
    "HttpSettings",
    "JobSettings",
    "LogSettings",
    "RobotSettings",
    "Role",
    "RsiSettings",
    "Settings",
    "StoreSettings",
    "TokenSettings",
    "load_settings",
]

ENV_PREFIX = "COMP_DAEMON_"
ENV_NESTED_DELIMITER = "__"
MIN_TOKEN_CHARS = 16

_CONFIG_FILE: contextvars.ContextVar[Path | None] = contextvars.ContextVar("_CONFIG_FILE", default=None)


def _base_dir() -> Path:
    path = _CONFIG_FILE.get()
    return path.parent if path is not None else Path.cwd()


def _resolve(path: Path) -> Path:
    path = path.expanduser()
    return path if path.is_absolute() else (_base_dir() / path)


class Role(IntEnum):
    """Roles in increasing power: each role may do everything the ones below it may."""

    viewer = 1
    operator = 2
    engineer = 3


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class HttpSettings(_Section):
    host: str = "127.0.0.1"
    port: int = Field(default=8080, ge=0, le=65535)
    max_upload_bytes: int = Field(default=20_000_000, ge=1024)
    max_batch_targets: int = Field(default=1000, ge=1)
    max_page_items: int = Field(default=500, ge=1)
    sse_keepalive_s: float = Field(default=15.0, gt=0)
    sse_queue_events: int = Field(default=256, ge=8)
    max_connections: int = Field(default=256, ge=2)
    header_timeout_s: float = Field(default=10.0, gt=0)
    body_timeout_s: float = Field(default=60.0, gt=0)
    write_timeout_s: float = Field(default=30.0, gt=0)
    status_interval_s: float = Field(default=0.25, gt=0, le=10)
    keep_alive_s: int = Field(default=5, ge=1)
    listen_backlog: int = Field(default=128, ge=1)
    max_concurrent_uploads: int = Field(default=2, ge=1)  # checking processes (bodies over 1 MiB)
    max_upload_bytes_in_flight: int = Field(default=40_000_000, ge=1024)


class StoreSettings(_Section):
    data_dir: Path = Path("var")
    db_filename: str = "comp-daemon.sqlite3"
    synchronous: Literal["full", "normal"] = "full"
    busy_timeout_ms: int = Field(default=5000, ge=0)
    event_retention_days: float = Field(default=90.0, gt=0)
    backup_dir: Path | None = None  # None: <data_dir>/backups
    backup_interval_h: float = Field(default=24.0, ge=0)  # 0: no scheduled backups
    backup_keep: int = Field(default=7, ge=1)

    @field_validator("data_dir")
    @classmethod
    def _relative_to_config(cls, value: Path) -> Path:
        return _resolve(value)

    @field_validator("backup_dir")
    @classmethod
    def _backup_relative_to_config(cls, value: Path | None) -> Path | None:
        return None if value is None else _resolve(value)

    @property
    def backup_path(self) -> Path:
        return self.backup_dir if self.backup_dir is not None else self.data_dir / "backups"

    @field_validator("db_filename")
    @classmethod
    def _plain_name(cls, value: str) -> str:
        if not value or "/" in value or "\\" in value or value in {".", ".."}:
            raise ValueError("must be a plain file name inside data_dir")
        return value

    @property
    def db_path(self) -> Path:
        return self.data_dir / self.db_filename


class TokenSettings(_Section):
    name: str = Field(min_length=1, max_length=64)
    role: Literal["viewer", "operator", "engineer"]
    token: SecretStr | None = None
    token_file: Path | None = None

    @model_validator(mode="after")
    def _one_source(self) -> TokenSettings:
        if (self.token is None) == (self.token_file is None):
            raise ValueError(f"token '{self.name}': give exactly one of 'token' or 'token_file'")
        if self.token_file is not None:
            path = _resolve(self.token_file)
            object.__setattr__(self, "token_file", path)
            try:
                text = path.read_text(encoding="utf-8").strip()
            except OSError as exc:
                raise ValueError(
                    f"token '{self.name}': cannot read token_file {path}: {exc.strerror}"
                ) from None
            object.__setattr__(self, "token", SecretStr(text))
        secret = self.token.get_secret_value() if self.token is not None else ""
        if len(secret) < MIN_TOKEN_CHARS or any(c.isspace() for c in secret):
            raise ValueError(
                f"token '{self.name}': must be at least {MIN_TOKEN_CHARS} characters without whitespace"
            )
        return self

    @property
    def secret(self) -> str:
        assert self.token is not None
        return self.token.get_secret_value()

    @property
    def role_level(self) -> Role:
        return Role[self.role]


class AuthSettings(_Section):
    tokens: list[TokenSettings] = Field(default_factory=list)
    anonymous_read: bool = False
    anonymous_metrics: bool = True

    @model_validator(mode="after")
    def _unique(self) -> AuthSettings:
        names = [t.name for t in self.tokens]
        dup = {n for n in names if names.count(n) > 1}
        if dup:
            raise ValueError(f"token names must be unique: {sorted(dup)}")
        secrets = [t.secret for t in self.tokens]
        if len(set(secrets)) != len(secrets):
            raise ValueError("two tokens have the same value")
        return self


class JobSettings(_Section):
    workers: int = Field(default=0, ge=0, le=64)  # 0: one per CPU the workers may use
    threads: int = Field(default=1, ge=1, le=256)  # numeric library threads per worker
    max_pending: int = Field(default=16, ge=1)
    nice: int = Field(default=10, ge=0, le=19)
    cpus: list[int] = Field(default_factory=list)  # CPUs of the workers; empty: all but the real-time one
    start_method: Literal["spawn", "forkserver"] = "spawn"
    max_runtime_s: float = Field(default=3600.0, gt=0)
    cancel_grace_s: float = Field(default=2.0, ge=0)

    @field_validator("cpus")
    @classmethod
    def _cpus(cls, value: list[int]) -> list[int]:
        if any(c < 0 for c in value):
            raise ValueError("CPU numbers are 0 or more")
        return sorted(set(value))


class RsiSettings(_Section):
    listen_host: str = "0.0.0.0"
    listen_port: int = Field(default=49152, ge=0, le=65535)
    controller_allow: list[str] = Field(default_factory=lambda: ["127.0.0.1"])
    cycle_ms: int = 12
    sen_type: str = Field(default="ImFree", min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_]+$")
    timeout_count: int = Field(default=10, ge=1)

    @field_validator("cycle_ms")
    @classmethod
    def _cycle(cls, value: int) -> int:
        if value not in (4, 12):
            raise ValueError("the RSI cycle is 4 (#IPO_FAST) or 12 (#IPO) ms")
        return value

    @field_validator("controller_allow")
    @classmethod
    def _addresses(cls, value: list[str]) -> list[str]:
        out = []
        for item in value:
            try:
                out.append(str(ipaddress.ip_address(item.strip())))
            except ValueError:
                raise ValueError(f"not an IP address: {item!r}") from None
        if not out:
            raise ValueError("at least one controller address is needed")
        return out


#: ``[realtime]`` keys of earlier versions, and why they are gone
_OWN_PROCESS = "the RSI endpoint, the grating readers and the loop always run in a process of their own"
REMOVED_REALTIME_KEYS = {
    "mode": _OWN_PROCESS,
    "thread": _OWN_PROCESS,
    "switch_interval_ms": "the interpreter's switch interval only mattered with the loop on a thread "
    "of the daemon, which is gone",
}


class RealtimeSettings(_Section):
    """The real-time process (comp_daemon.rt.child): the RSI endpoint, the grating readers and the
    loop in a process of their own, on ``cpu`` at ``SCHED_FIFO`` ``priority`` where permitted.

    The defaults are what config.example.toml recommends (SCHED_FIFO 20, CPU wake-up latency 0 µs):
    without them a 4 ms loop had 7–8 times the late replies of a bare echo. Where the system refuses
    them (no ``CAP_SYS_NICE``/``LimitRTPRIO``, no access to ``/dev/cpu_dma_latency``) the process
    runs without and says so in the one start-up line; ``priority = 0`` and
    ``cpu_wakeup_latency_us = -1`` ask for neither.

    Keys of earlier versions (:data:`REMOVED_REALTIME_KEYS`) are refused by name with the reason.
    """

    cpu: int | Literal["auto", "none"] = "auto"
    priority: int = Field(default=20, ge=0, le=99)  # 0: normal scheduling
    keep_jobs_off_cpu: bool = True
    cpu_wakeup_latency_us: int = Field(default=0, ge=-1, le=100_000)  # -1: no PM QoS request

    @model_validator(mode="before")
    @classmethod
    def _removed_keys(cls, data: Any) -> Any:
        if isinstance(data, dict):
            for key, why in REMOVED_REALTIME_KEYS.items():
                if key in data:
                    raise ValueError(f"realtime.{key} is no longer a setting: {why}; remove it")
        return data

    @field_validator("cpu")
    @classmethod
    def _cpu(cls, value: int | str) -> int | str:
        if isinstance(value, int) and value < 0:
            raise ValueError("a CPU number is 0 or more (or 'auto', or 'none')")
        return value


class EncoderJointSettings(_Section):
    joint: int = Field(ge=1, le=6)
    port: str = Field(min_length=1)
    radius_mm: float = Field(gt=0)
    resolution_nm: float = Field(default=50.0, gt=0)
    bits: Literal[26, 32] = 32


class EncoderSettings(_Section):
    poll_period_ms: float = Field(default=12.0, gt=0)
    poll_lead_ms: float = Field(default=3.0, gt=0)
    stale_after_ms: float = Field(default=36.0, gt=0)
    reply_timeout_ms: float = Field(default=10.0, gt=0)
    reconnect_initial_ms: float = Field(default=250.0, gt=0)
    reconnect_max_ms: float = Field(default=5000.0, gt=0)
    baudrate: int = Field(default=115200, gt=0)
    joints: list[EncoderJointSettings] = Field(default_factory=list)

    @model_validator(mode="after")
    def _consistent(self) -> EncoderSettings:
        numbers = [j.joint for j in self.joints]
        if len(set(numbers)) != len(numbers):
            raise ValueError(f"each joint may have one grating: joints {numbers}")
        ports = [j.port for j in self.joints]
        if len(set(ports)) != len(ports):
            raise ValueError("two joints share a serial port")
        if self.reconnect_max_ms < self.reconnect_initial_ms:
            raise ValueError("reconnect_max_ms must be >= reconnect_initial_ms")
        if self.poll_lead_ms >= self.poll_period_ms:
            raise ValueError(
                f"poll_lead_ms ({self.poll_lead_ms}) must be less than poll_period_ms ({self.poll_period_ms})"
            )
        return self


class ControllerSettings(_Section):
    kp: float = Field(default=0.05, ge=0)
    kd: float = Field(default=0.65, ge=0)
    rough_step_deg: float = Field(default=0.002, gt=0)
    rough_threshold_deg: float = Field(default=0.007, gt=0)
    max_step_deg: float = Field(default=0.01, gt=0)
    max_total_deg: float = Field(default=0.5, gt=0)
    settle_tolerance_deg: float = Field(default=0.001, gt=0)
    settle_dwell_ms: float = Field(default=240.0, ge=0)
    move_timeout_s: float = Field(default=120.0, gt=0)
    settle_timeout_s: float = Field(default=10.0, gt=0)

    @model_validator(mode="after")
    def _consistent(self) -> ControllerSettings:
        if self.max_step_deg < self.rough_step_deg:
            raise ValueError("max_step_deg must be >= rough_step_deg")
        if self.max_total_deg < self.max_step_deg:
            raise ValueError("max_total_deg must be >= max_step_deg")
        if self.settle_tolerance_deg >= self.rough_threshold_deg:
            raise ValueError("settle_tolerance_deg must be < rough_threshold_deg")
        return self


class CompensationSettings(_Section):
    """What a compensated target may do (:class:`comp_daemon.models.compensation.CompensationLimits`).

    ``max_axis_change_deg``: largest change of any axis from the nominal solution;
    ``wrist_singularity_deg``: targets whose axes 4 and 6 are nearer than this to in line (|A5|) are
    refused; ``hull_margin_deg``: how far beyond the sampled axis ranges of the model a target may lie;
    ``mapping``: how a compensated target becomes axis values, ``"six-axis"`` (inverse kinematics of
    every axis) or ``"three-axis"`` (seed 000's mapping onto joints 1–3, the wrist from the nominal
    solution); the limits apply to both. Its former name ``"seed000"`` is still read, as
    ``"three-axis"``, with a warning that names the new one (an old configuration file keeps the
    cell running; the warning says what to write).
    """

    max_axis_change_deg: float = Field(default=DEFAULT_LIMITS.max_axis_change_deg, gt=0, le=10.0)
    wrist_singularity_deg: float = Field(default=DEFAULT_LIMITS.wrist_singularity_deg, ge=0, lt=90.0)
    hull_margin_deg: float = Field(default=DEFAULT_LIMITS.hull_margin_deg, ge=0, le=360.0)
    mapping: JointMapping = "six-axis"

    @field_validator("mapping", mode="before")
    @classmethod
    def _former_mapping_name(cls, value: Any) -> Any:
        if isinstance(value, str) and value in RENAMED_MAPPINGS:
            warnings.warn(
                f"[compensation] mapping: {renamed_mapping_note(value)}", FutureWarning, stacklevel=2
            )
            return RENAMED_MAPPINGS[value]
        return value

    def limits(self) -> CompensationLimits:
        return CompensationLimits(self.max_axis_change_deg, self.wrist_singularity_deg, self.hull_margin_deg)


class RobotSettings(_Section):
    name: str = "kr210"

    @field_validator("name")
    @classmethod
    def _preset_or_path(cls, value: str) -> str:
        from comp_daemon.robot.description import PRESETS

        if value in PRESETS:
            return value
        return str(_resolve(Path(value)))


class LogSettings(_Section):
    level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = "INFO"
    format: Literal["json", "console"] = "json"


class Settings(BaseSettings):
    """Everything the daemon can be told; see ``config.example.toml``."""

    model_config = SettingsConfigDict(
        env_prefix=ENV_PREFIX,
        env_nested_delimiter=ENV_NESTED_DELIMITER,
        extra="forbid",
        frozen=True,
    )

    http: HttpSettings = Field(default_factory=HttpSettings)
    store: StoreSettings = Field(default_factory=StoreSettings)
    auth: AuthSettings = Field(default_factory=AuthSettings)
    jobs: JobSettings = Field(default_factory=JobSettings)
    rsi: RsiSettings = Field(default_factory=RsiSettings)
    realtime: RealtimeSettings = Field(default_factory=RealtimeSettings)
    encoders: EncoderSettings = Field(default_factory=EncoderSettings)
    controller: ControllerSettings = Field(default_factory=ControllerSettings)
    compensation: CompensationSettings = Field(default_factory=CompensationSettings)
    robot: RobotSettings = Field(default_factory=RobotSettings)
    log: LogSettings = Field(default_factory=LogSettings)

    @classmethod
    def settings_customise_sources(
        cls,
        settings_cls: type[BaseSettings],
        init_settings: PydanticBaseSettingsSource,
        env_settings: PydanticBaseSettingsSource,
        dotenv_settings: PydanticBaseSettingsSource,
        file_secret_settings: PydanticBaseSettingsSource,
    ) -> tuple[PydanticBaseSettingsSource, ...]:
        path = _CONFIG_FILE.get()
        sources: list[PydanticBaseSettingsSource] = [init_settings, env_settings]
        if path is not None:
            sources.append(TomlConfigSettingsSource(settings_cls, toml_file=path))
        return tuple(sources)


@contextmanager
def _config_file(path: Path | None) -> Iterator[None]:
    token = _CONFIG_FILE.set(path)
    try:
        yield
    finally:
        _CONFIG_FILE.reset(token)


def load_settings(path: str | Path | None = None, **overrides: Any) -> Settings:
    """Settings from ``path`` (TOML) with environment overrides; ``overrides`` win over both.

    Raises ``FileNotFoundError`` for a missing file, ``tomllib.TOMLDecodeError`` for bad TOML and
    ``pydantic.ValidationError`` (naming the section and key) for bad values.
    """
    file_path = None
    if path is not None:
        file_path = Path(path).expanduser().resolve()
        if not file_path.is_file():
            raise FileNotFoundError(f"configuration file not found: {file_path}")
        import tomllib

        tomllib.loads(file_path.read_text(encoding="utf-8"))  # a clear syntax error before pydantic's
    with _config_file(file_path):
        return Settings(**overrides)
