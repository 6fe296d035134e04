"""The daemon's settings: one TOML file plus ``EYESERVER_`` environment overrides.

Sources, from lowest to highest priority:

1. the defaults below, which need no file at all: the simulated room, the user's data directory
   and ``127.0.0.1:8000``;
2. the TOML configuration file given to :meth:`Settings.load` (``eyeserver serve --config FILE``),
   with the keys of :class:`Settings` at its top level;
3. environment variables named ``EYESERVER_`` + the key in upper case (``EYESERVER_DATA_DIR``,
   ``EYESERVER_PORT``); nested keys, once there are any, join their parts with ``__``.
   Variables with the prefix that name no key, and empty ones, are ignored;
4. explicit overrides passed to :meth:`Settings.load`, i.e. the command-line flags
   (``--host``, ``--port``).

Relative paths in the TOML file are taken relative to the file's own directory, so a file can
name a room file next to it; relative paths elsewhere are relative to the working directory.
A leading ``~`` is expanded everywhere.

Every problem (a missing or malformed file, an unknown key, a value of the wrong type) raises
:class:`~eyeserver.errors.ConfigError` with a message that names where the value came from (the
file, the environment variable or the override) and the key.
"""

from __future__ import annotations

import os
import tomllib
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from contextvars import ContextVar
from pathlib import Path
from typing import Annotated, Any, Literal, Self

import platformdirs
from pydantic import Field, SecretStr, ValidationError, field_validator
from pydantic_core import ErrorDetails
from pydantic_settings import (
    BaseSettings,
    NoDecode,
    PydanticBaseSettingsSource,
    SettingsConfigDict,
    SettingsError,
    TomlConfigSettingsSource,
)

from eyeserver.core.validation import StrictModel
from eyeserver.errors import ConfigError

__all__ = ["ENV_PREFIX", "MIN_TOKEN_LENGTH", "ROLES", "ClientCertMode", "LogLevel", "QaSettings",
           "QaThresholds", "Role", "Settings", "TokenConfig"]

#: Prefix of the environment variables that override settings.
ENV_PREFIX = "EYESERVER_"

LogLevel = Literal["critical", "error", "warning", "info", "debug"]

Role = Literal["operator", "physicist"]
ROLES: tuple[Role, ...] = ("operator", "physicist")
"""The roles, each allowed what the ones before it are: an ``operator`` measures and reads, a
``physicist`` also calibrates, deletes and configures."""

ClientCertMode = Literal["none", "optional", "required"]

MIN_TOKEN_LENGTH = 16
"""Shortest bearer token accepted: a guessable token protects nothing."""


class TokenConfig(StrictModel):
    """One bearer token: who holds it (the name the audit trail records) and its role."""

    name: str = Field(min_length=1, description="Who holds the token (recorded in the audit).")
    role: Role = Field(description="operator or physicist.")
    token: SecretStr = Field(description=f"The secret, at least {MIN_TOKEN_LENGTH} characters.")

    @field_validator("token", mode="after")
    @classmethod
    def _long_enough(cls, value: SecretStr) -> SecretStr:
        if len(value.get_secret_value()) < MIN_TOKEN_LENGTH:
            raise ValueError(f"a token needs at least {MIN_TOKEN_LENGTH} characters")
        return value

# The configuration file of the ``load`` call in progress. ``settings_customise_sources`` is a
# classmethod pydantic-settings calls without our arguments, so the file travels this way; a
# context variable keeps concurrent loads (threads, tasks) apart.
_config_file: ContextVar[Path | None] = ContextVar("eyeserver_config_file", default=None)

# Keys holding paths; relative values in the TOML file are resolved against the file's directory.
_PATH_KEYS = ("data_dir", "room_file", "tls_certfile", "tls_keyfile", "tls_ca_certs",
              "audit_log")
# Keys whose values are never repeated in an error message.
_SECRET_KEYS = ("tokens",)


class QaThresholds(StrictModel):
    """The daily QA's pass limits, each figure at most this (mm; docs/qa.md justifies them).

    AAPM TG-302 asks ≤ 1 mm of an SGRT system's daily static localisation; a proton beam on an
    eye, given at PSI only within 0.2 mm of the plan, needs QA limits well inside that 0.2 mm
    tolerance and above what the healthy system measures (docs/qa.md gives the simulated
    room's figures beside each).
    """

    localisation_mm: float = Field(
        default=0.10, gt=0, le=5.0,
        description="The phantom's ball centre, located by its dots, against the drawing's QA "
        "position: half the 0.2 mm clinical tolerance.")
    surface_mm: float = Field(
        default=0.05, gt=0, le=5.0,
        description="Median |distance| of the measured surface to the drawing placed where the "
        "phantom stands: the design's surface goal.")
    fiducial_mm: float = Field(
        default=0.05, gt=0, le=5.0,
        description="Median distance of the triangulated dots to the drawing's, after the "
        "phantom's placement: the design's fiducial goal.")
    cross_unit_mm: float = Field(
        default=0.05, gt=0, le=5.0,
        description="Median |distance| between the two units' surfaces where both see the "
        "phantom.")
    static_noise_mm: float = Field(
        default=0.03, gt=0, le=5.0,
        description="Frame-to-frame height spread of the still phantom, worst camera: the "
        "design's repeatability goal.")
    drift_mm: float = Field(
        default=0.05, gt=0, le=5.0,
        description="Change of the units' relative view of the phantom since the active "
        "calibration's QA baseline: a quarter of the clinical tolerance.")


class QaSettings(StrictModel):
    """The daily QA and its lockout (``[qa]`` in the TOML file; ``EYESERVER_QA__REQUIRED``,
    ``EYESERVER_QA__THRESHOLDS__SURFACE_MM`` … in the environment)."""

    required: bool = Field(
        default=True,
        description="Position verification and tracking answer 409 until the day's QA passed "
        "with the active calibration (or a physicist overrode it). Off only for benches, tests "
        "and demonstrations.")
    max_consecutive_failures: int = Field(
        default=1, ge=1, le=10,
        description="Failed QA runs in a row, after the day's pass, that lock again (1: any "
        "failure does).")
    frames: int = Field(
        default=4, ge=2, le=20,
        description="Captures of the still phantom a QA run takes (the static noise needs 2).")
    thresholds: QaThresholds = Field(default_factory=QaThresholds)


def _default_data_dir() -> Path:
    # platformdirs only computes the path here (XDG_DATA_HOME on Linux); nothing is created.
    return platformdirs.user_data_path("eyeserver", appauthor=False)


class _ConfigFileSource(TomlConfigSettingsSource):
    """The TOML file, with relative paths taken relative to the file's directory."""

    # ``_read_file`` is pydantic-settings' per-file hook (not public API; the relative-path test
    # in tests/test_config.py catches a change on upgrade).
    def _read_file(self, file_path: Any) -> dict[str, Any]:
        data = super()._read_file(file_path)
        base = Path(file_path).parent
        for key in _PATH_KEYS:
            value = data.get(key)
            if isinstance(value, str):
                path = Path(value).expanduser()
                if not path.is_absolute():
                    data[key] = str(base / path)
        return data


class Settings(BaseSettings):
    """Everything the daemon can be told before it starts.

    Keys (TOML key = field name; environment variable = ``EYESERVER_`` + key in upper case):

    ``data_dir``
        Directory for the database, images, point clouds and calibrations. Default: the user's
        data directory (``~/.local/share/eyeserver`` on Linux). Created on demand by
        :meth:`ensure_data_dir`, never at import.
    ``host``
        Address the HTTP API listens on. Default ``127.0.0.1`` (this machine only).
    ``port``
        TCP port of the HTTP API. Default ``8000``.
    ``room``
        ``sim`` (default): the simulated room; ``devices``: a room of real devices, which
        ``room_file`` names (docs/room-file.md).
    ``room_file``
        TOML file describing the room: the simulated room's (unset: the built-in default room)
        or the real devices' (required with ``room = "devices"``).
    ``log_level``
        One of ``critical``, ``error``, ``warning``, ``info``, ``debug``. Default ``info``.
    ``log_json``
        ``true`` for one JSON object per log line on stderr (default), ``false`` for plain text.
    ``max_upload_mb``
        Largest upload (a calibration archive) the API accepts, and the most it may unpack to,
        in MiB. Default ``200``.
    ``event_queue_size``
        Events held for each client of the live event stream (``/api/v1/ws/events``) that
        reads too slowly; when full, its oldest event is dropped. Default ``256``.
    ``ws_stall_s``
        A client of ``/api/v1/ws/events`` or ``/api/v1/ws/pose`` whose socket accepted nothing
        for this long (it stopped reading, its buffers are full) is sent a last ``dropped``
        notice and closed with 4008. Default ``10`` seconds: well before the 40 s after which
        the server's keep-alive would cut it off without a word.
    ``acquisition_queue``
        Hardware jobs (captures, device settings) that may wait while one runs; one more is
        refused with HTTP 503. Default ``8``.
    ``reconstruction_queue``
        Reconstructions that may wait while one runs; one more is refused with HTTP 503.
        Default ``4``.
    ``job_queue``
        Long jobs (batch reconstructions, calibration solves) that may wait while one runs;
        one more is refused with HTTP 503. Default ``8``.
    ``tracking_workers``
        Worker processes that reconstruct and fit live tracking's frames: the first takes
        every frame it is free for, the next ones the frames it is busy through. Default
        ``2``: a global fit of the whole images (after the eye was lost, ≈ 1 s) leaves the
        second worker following the frames; with one, a 60-s run on two cores dropped 24
        frames after the saccade (``eyeserver bench tracking --workers N`` measures it).
    ``public_api_docs``
        ``true`` (default): the OpenAPI document (``/api/v1/openapi.json``) and its interactive
        view (``/api/v1/docs``) are open without a token, like ``/api/v1/health``; they
        describe the API, not its data. ``false``: the document needs a token of any role and
        the interactive view is off.
    ``tracking_deadline_ms``
        The fail-safe beam hold of live tracking: when no processed frame has been published
        for this long, the daemon holds the beam itself and says why on ``/api/v1/ws/pose``.
        Default ``80`` (two camera periods).
    ``tokens``
        The bearer tokens the API accepts. In the file, named tokens as an array of tables
        (``[[tokens]]`` with ``name``, ``role``, ``token``); in ``EYESERVER_TOKENS``,
        comma-separated ``role:token`` pairs, the role doubling as the name. Empty (default):
        the daemon generates one token per role in ``DATA_DIR/tokens.toml`` at its first start.
    ``tls_certfile``, ``tls_keyfile``
        PEM certificate (chain) and private key: the API is served over HTTPS. Unset (default):
        plain HTTP, for loopback only. Checked by :func:`eyeserver.tls.uvicorn_ssl_options`.
    ``tls_ca_certs``
        PEM file of the CA(s) that sign client certificates.
    ``tls_client_cert``
        ``none`` (default), ``optional`` or ``required``: whether clients must present a
        certificate signed by ``tls_ca_certs`` (mutual TLS); the bearer token is needed anyway.
    ``audit_log``
        The append-only JSON-lines audit file. Default ``DATA_DIR/audit.jsonl``.
    ``retention_days``
        Captures older than this many days are deleted (audited as ``retention``) by an hourly
        task. Unset (default): captures are kept forever.
    ``qa``
        The daily QA (:class:`QaSettings`, a ``[qa]`` table): ``required`` (default ``true``:
        position verification and tracking answer 409 until the day's QA has passed with the
        active calibration), ``max_consecutive_failures`` (``1``), ``frames`` (``4``) and the
        ``[qa.thresholds]`` in mm (docs/qa.md).

    Build it with :meth:`load`; constructing ``Settings()`` directly reads only the defaults and
    the environment.
    """

    model_config = SettingsConfigDict(
        env_prefix=ENV_PREFIX,
        env_nested_delimiter="__",
        # ``EYESERVER_ROOM_FILE=`` (e.g. in a systemd unit) means "not set", not the path "".
        env_ignore_empty=True,
        # Unknown EYESERVER_* variables are ignored (other tools may define their own); unknown keys
        # in the file or the overrides are rejected by ``load`` instead, since there a misspelt key
        # must not pass silently.
        extra="ignore",
        validate_default=True,
    )

    data_dir: Path = Field(
        default_factory=_default_data_dir,
        description="Directory for the database, images, point clouds and calibrations "
        "(default: the user's data directory). Created on demand.",
    )
    host: str = Field(
        default="127.0.0.1",
        min_length=1,
        description="Address the HTTP API listens on.",
    )
    port: int = Field(
        default=8000,
        ge=1,
        le=65535,
        description="TCP port of the HTTP API.",
    )
    room: Literal["sim", "devices"] = Field(
        default="sim",
        description="sim: the simulated room; devices: the real devices room_file names.",
    )
    room_file: Path | None = Field(
        default=None,
        description="TOML file describing the room: the simulated room's (unset for the built-in "
        "default room) or the real devices' (required with room = devices).",
    )
    log_level: LogLevel = Field(
        default="info",
        description="Lowest level that is logged: critical, error, warning, info or debug.",
    )
    log_json: bool = Field(
        default=True,
        description="Log one JSON object per line on stderr (true) or plain text (false).",
    )
    max_upload_mb: int = Field(
        default=200,
        ge=1,
        description="Largest upload (a calibration archive) the API accepts, and the most it "
        "may unpack to, in MiB.",
    )
    event_queue_size: int = Field(
        default=256,
        ge=1,
        description="Events held for each slow client of the live event stream; when full, "
        "its oldest event is dropped.",
    )
    ws_stall_s: float = Field(
        default=10.0,
        ge=0.1,
        le=30.0,
        description="A stream client whose socket accepted nothing for this long (seconds) "
        "gets a last dropped notice and is closed with 4008.",
    )
    acquisition_queue: int = Field(
        default=8,
        ge=1,
        description="Hardware jobs (captures, device settings) that may wait while one runs; "
        "one more is refused with HTTP 503.",
    )
    reconstruction_queue: int = Field(
        default=4,
        ge=1,
        description="Reconstructions that may wait while one runs; one more is refused with "
        "HTTP 503.",
    )
    tracking_workers: int = Field(
        default=2,
        ge=1,
        le=8,
        description="Worker processes for live tracking's frames, each on its own frames.",
    )
    public_api_docs: bool = Field(
        default=True,
        description="The OpenAPI document and /docs open without a token (false: the document "
        "needs one, /docs is off).",
    )
    tracking_deadline_ms: float = Field(
        default=80.0,
        ge=20.0,
        le=2000.0,
        description="Live tracking holds the beam itself when no processed frame has been "
        "published for this long.",
    )
    job_queue: int = Field(
        default=8,
        ge=1,
        description="Long jobs (batch reconstructions, calibration solves) that may wait while "
        "one runs; one more is refused with HTTP 503.",
    )

    tokens: Annotated[tuple[TokenConfig, ...], NoDecode] = Field(
        default=(),
        description="Bearer tokens with their holder's name and role; empty: generated in "
        "DATA_DIR/tokens.toml at the first start.",
    )

    tls_certfile: Path | None = Field(
        default=None,
        description="PEM certificate (chain) for HTTPS; unset: plain HTTP.",
    )
    tls_keyfile: Path | None = Field(
        default=None,
        description="PEM private key of tls_certfile.",
    )
    tls_ca_certs: Path | None = Field(
        default=None,
        description="PEM file of the CAs that sign client certificates.",
    )
    tls_client_cert: ClientCertMode = Field(
        default="none",
        description="Client certificates (signed by tls_ca_certs): none, optional or required.",
    )
    audit_log: Path | None = Field(
        default=None,
        description="Append-only JSON-lines audit file; unset: DATA_DIR/audit.jsonl.",
    )
    retention_days: float | None = Field(
        default=None,
        gt=0,
        description="Delete captures older than this many days (audited); unset: keep forever.",
    )
    qa: QaSettings = Field(
        default_factory=QaSettings,
        description="The daily QA: whether it locks verification and tracking, its captures "
        "and its thresholds (docs/qa.md).",
    )

    @field_validator("tokens", mode="before")
    @classmethod
    def _parse_token_pairs(cls, value: object) -> object:
        # EYESERVER_TOKENS="operator:s3cret...,physicist:other..." (NoDecode: not JSON).
        if not isinstance(value, str):
            return value
        tokens = []
        for pair in filter(None, (part.strip() for part in value.split(","))):
            role, colon, token = pair.partition(":")
            if not colon:
                raise ValueError(f"expected comma-separated role:token pairs, got {pair[:12]!r}…"
                                 if len(pair) > 12 else
                                 f"expected comma-separated role:token pairs, got {pair!r}")
            tokens.append({"name": role.strip(), "role": role.strip(), "token": token.strip()})
        return tokens

    @field_validator("tokens", mode="after")
    @classmethod
    def _unique_tokens(cls, value: tuple[TokenConfig, ...]) -> tuple[TokenConfig, ...]:
        secrets = [t.token.get_secret_value() for t in value]
        if len(set(secrets)) != len(secrets):
            raise ValueError("the same token is given twice (each holder needs their own)")
        return value

    @field_validator("data_dir", "room_file", "tls_certfile", "tls_keyfile", "tls_ca_certs",
                     "audit_log", mode="after")
    @classmethod
    def _expand_user(cls, value: Path | None) -> Path | None:
        return None if value is None else value.expanduser()

    @field_validator("log_level", mode="before")
    @classmethod
    def _lower_case_level(cls, value: object) -> object:
        return value.lower() if isinstance(value, str) else value

    @classmethod
    def settings_customise_sources(
        cls,
        settings_cls: type[BaseSettings],
        init_settings: PydanticBaseSettingsSource,
        env_settings: PydanticBaseSettingsSource,
        dotenv_settings: PydanticBaseSettingsSource,
        file_secret_settings: PydanticBaseSettingsSource,
    ) -> tuple[PydanticBaseSettingsSource, ...]:
        """Order the sources: overrides > environment > TOML file > defaults.

        Dotenv files and secret directories are not used.
        """
        return (
            init_settings,
            env_settings,
            _ConfigFileSource(settings_cls, toml_file=_config_file.get()),
        )

    @classmethod
    def load(cls, config_file: Path | None = None, **overrides: Any) -> Self:
        """Read the settings from their sources.

        Parameters
        ----------
        config_file
            The TOML configuration file, or ``None`` for none. It must exist when given.
        **overrides
            Values that beat every other source (command-line flags). Overrides that are
            ``None`` are ignored, so unset optional flags can be passed through as they are.

        Raises
        ------
        ConfigError
            The file is missing, unreadable or not TOML, or a key is unknown or has a bad value;
            the message names the file or environment variable and the key.
        """
        given = {key: value for key, value in overrides.items() if value is not None}
        known = ", ".join(cls.model_fields)
        for key in given:
            if key not in cls.model_fields:
                raise ConfigError(f"override '{key}': unknown key (known keys: {known})")
        file_data: dict[str, Any] = {}
        if config_file is not None:
            file_data = _read_toml(config_file)
            for key in file_data:
                if key not in cls.model_fields:
                    raise ConfigError(
                        f"{config_file}: key '{key}': unknown key (known keys: {known})"
                    )
        try:
            with _loading(config_file):
                return cls(**given)
        except ValidationError as exc:
            problems = "; ".join(
                _describe_error(error, config_file, file_data, given) for error in exc.errors()
            )
            raise ConfigError(f"invalid configuration: {problems}") from exc
        except SettingsError as exc:
            # Raised for values pydantic-settings cannot even parse (e.g. JSON in an environment
            # variable for a structured key); its message already names the field.
            raise ConfigError(f"invalid configuration: {exc}") from exc

    def ensure_data_dir(self) -> Path:
        """Create :attr:`data_dir` (and its parents) if missing and return it.

        Raises
        ------
        ConfigError
            The directory cannot be created or the path exists but is not a directory.
        """
        try:
            self.data_dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise ConfigError(
                f"data_dir {self.data_dir}: cannot create directory: {exc.strerror or exc}"
            ) from exc
        return self.data_dir


@contextmanager
def _loading(config_file: Path | None) -> Iterator[None]:
    token = _config_file.set(config_file)
    try:
        yield
    finally:
        _config_file.reset(token)


def _read_toml(config_file: Path) -> dict[str, Any]:
    """Parse the file once up front, for error messages that name it and its keys."""
    try:
        with config_file.expanduser().open("rb") as stream:
            return tomllib.load(stream)
    except FileNotFoundError as exc:
        raise ConfigError(f"{config_file}: configuration file not found") from exc
    except IsADirectoryError as exc:
        raise ConfigError(f"{config_file}: is a directory, not a configuration file") from exc
    except OSError as exc:
        raise ConfigError(f"{config_file}: cannot read: {exc.strerror or exc}") from exc
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{config_file}: not valid TOML: {exc}") from exc


def _env_variable(key: str) -> str | None:
    """The environment variable that sets top-level ``key``, if one is set."""
    wanted = (ENV_PREFIX + key).lower()
    for name in os.environ:
        # Settings are matched case-insensitively, as pydantic-settings does by default.
        if name.lower() == wanted or name.lower().startswith(wanted + "__"):
            return name
    return None


def _describe_error(
    error: ErrorDetails,
    config_file: Path | None,
    file_data: Mapping[str, Any],
    overrides: Mapping[str, Any],
) -> str:
    location = [str(part) for part in error["loc"]]
    key = ".".join(location) or "<settings>"
    top = location[0] if location else ""
    if top in overrides:
        where = f"override '{key}'"
    elif (variable := _env_variable(top)) is not None:
        where = f"environment variable {variable}"
    elif top in file_data:
        where = f"{config_file}: key '{key}'"
    else:
        where = f"key '{key}'"
    if top in _SECRET_KEYS:
        return f"{where}: {error['msg']}"  # never echo a secret into a log or a terminal
    return f"{where}: {error['msg']} (got {error['input']!r})"
