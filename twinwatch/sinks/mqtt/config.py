"""The ``[outputs.mqtt]`` table: the broker connection's keys (shared with the Sparkplug B
output), TLS and Home Assistant discovery (docs/mqtt.md).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import ClassVar, Literal, Self

from pydantic import Field, StrictFloat, StrictInt, field_validator, model_validator

from twinwatch._table import StrictTable
from twinwatch.sinks.base import SinkConfig

# A topic level: no wildcards, no NUL; '/' separates levels.
_LEVEL_RE = re.compile(r"^[^#+\x00/]+$")


def check_topic(value: str, what: str) -> str:
    """A topic (prefix) by MQTT's rules (MQTT 3.1.1 Section 4.7): non-empty levels, no
    wildcards, no NUL, at most 65535 bytes of UTF-8, and not a ``$`` topic."""
    if not value or any(_LEVEL_RE.match(level) is None for level in value.split("/")):
        raise ValueError(f"{what} {value!r} must be non-empty topic levels separated by '/', "
                         f"without the wildcards '+' and '#', NUL (and no leading or trailing "
                         f"'/')")
    if value.startswith("$"):
        raise ValueError(f"{what} {value!r} starts with '$': such topics are the broker's "
                         f"own ($SYS), not for applications (MQTT 3.1.1 Section 4.7.2)")
    if len(value.encode("utf-8")) > 60_000:  # the machine and the suffixes need room
        raise ValueError(f"{what} is {len(value.encode('utf-8'))} bytes: an MQTT topic is "
                         f"at most 65535 bytes with its machine and suffix")
    return value


class MqttTlsConfig(StrictTable):
    """``[outputs.mqtt.tls]``: TLS to the broker (``port`` is then usually 8883). Paths are
    relative to the configuration file's directory; the private key is a secret (refused when
    others can read it: install it ``0640 root:twinwatch``).
    """

    ca_certs: str | None = Field(None,
                                 description="the broker's CA (PEM); unset: the system's CAs")
    certfile: str | None = Field(None,
                                 description="our client certificate (PEM), if asked for")
    keyfile: str | None = Field(None, description="its private key (PEM; a secret: 0640)")
    verify_hostname: bool = Field(True,
                                  description="check the broker's name against its certificate")

    FILES: ClassVar[tuple[str, ...]] = ("ca_certs", "certfile", "keyfile")
    SECRET_FILES: ClassVar[tuple[str, ...]] = ("keyfile",)

    @model_validator(mode="after")
    def _pair(self) -> Self:
        if bool(self.certfile) != bool(self.keyfile):
            raise ValueError("certfile and keyfile go together (a client certificate and its "
                             "private key)")
        return self


class HomeAssistantConfig(StrictTable):
    """``[outputs.mqtt.home_assistant]``: Home Assistant's MQTT device discovery."""

    discovery: bool = Field(False, description="announce a Home Assistant device; false clears it")
    prefix: str = Field("homeassistant",
                        description="Home Assistant's discovery prefix (birth on <prefix>/status)")
    device_name: str | None = Field(None,
                                    description="its name; unset: the machine name")

    @field_validator("prefix")
    @classmethod
    def _prefix(cls, value: str) -> str:
        return check_topic(value, "prefix")


class MqttConnectionConfig(SinkConfig):
    """The broker connection and the outbox's pace: the keys ``[outputs.mqtt]`` shares with
    ``[outputs.sparkplug]`` (:mod:`twinwatch.sinks.sparkplug`)."""

    host: str = Field("127.0.0.1", min_length=1, description="the broker's host name or address")
    port: StrictInt = Field(1883, ge=1, le=65535, description="the broker's port (8883 for TLS)")
    client_id: str | None = Field(None, min_length=1, max_length=128,
                                  description="unique per broker; unset: twinwatch-<machine>")
    username: str | None = Field(None, min_length=1,
                                 description="user name, if the broker asks for one")
    password_file: str | None = Field(None,
                                      description="the password's file (first line; a secret)")
    password: str | None = Field(None,
                                 description="the password inline (the file is then a secret)")
    tls: MqttTlsConfig | None = Field(None, description="TLS to the broker")
    keepalive: StrictInt = Field(
        30, ge=5, le=65535,
        description="s between pings; silent for 1.5x: offline (last will)")
    qos: Literal[1, 2] = Field(1, description="1: at least once; 2: exactly once while connected")
    inflight: StrictInt = Field(10, ge=1, le=1000,
                                description="windows sent, not yet acknowledged, at most")
    rate: StrictFloat = Field(20.0, gt=0, description="windows a second, at most, when catching up")
    reconnect_min: StrictFloat = Field(0.5, gt=0,
                                       description="s to the first retry; doubles to reconnect_max")
    reconnect_max: StrictFloat = Field(30.0, gt=0,
                                       description="s, the longest retry delay (+-25 % jitter)")
    ack_timeout: StrictFloat = Field(
        30.0, gt=0, allow_inf_nan=False,
        description="s a window may wait for the broker's acknowledgement before DEGRADED")
    connect_timeout: StrictFloat = Field(
        5.0, gt=0, description="s, one connection attempt's timeout")
    close_timeout: StrictFloat = Field(5.0, ge=0,
                                       description="s at stop to deliver what is pending "
                                       "(reconnecting every second meanwhile if the broker "
                                       "is away)")
    memory_outbox: StrictInt = Field(10_000, ge=1,
                                     description="windows kept in memory without a state database")

    @field_validator("client_id")
    @classmethod
    def _client_id(cls, value: str | None) -> str | None:
        # MQTT 3.1.1 Section 3.1.3.1: a UTF-8 string; with a NUL or control character nothing
        # is delivered
        if value is not None and any(ord(c) < 0x20 or ord(c) == 0x7F for c in value):
            raise ValueError("client_id must not contain NUL or control characters")
        return value

    @model_validator(mode="after")
    def _check(self) -> Self:
        if self.password is not None and self.password_file is not None:
            raise ValueError("give password_file or password, not both")
        if (self.password is not None or self.password_file is not None) and not self.username:
            raise ValueError("a password needs a username")
        if self.reconnect_min > self.reconnect_max:
            raise ValueError("reconnect_min must not exceed reconnect_max")
        return self

    def input_files(self) -> dict[str, str]:
        """Key -> path of the files read at open (certificates, key, password file)."""
        out = {}
        if self.tls is not None:
            out.update({f"tls.{k}": v for k in MqttTlsConfig.FILES
                        if (v := getattr(self.tls, k))})
        if self.password_file:
            out["password_file"] = self.password_file
        return out

    def secret_input_files(self) -> dict[str, str]:
        """The private key and the password file: refused when others can read them."""
        secret = {f"tls.{k}" for k in MqttTlsConfig.SECRET_FILES} | {"password_file"}
        return {k: v for k, v in self.input_files().items() if k in secret}

    def inline_secret_keys(self) -> list[str]:
        """``password`` written in the configuration itself."""
        return ["password"] if self.password is not None else []

    def exclusive_resources(self, cwd: Path) -> set[str]:
        """The client id at the broker (a second connection with it would take the session
        over)."""
        return {f"mqtt://{self.host}:{self.port}/{self.client_id or ''}"}


class MqttConfig(MqttConnectionConfig):
    """``[outputs.mqtt]``: the MQTT output (see the module docstring; docs/mqtt.md has an
    example).
    """

    topic_prefix: str = Field("twinwatch",
                              description="<prefix>/<machine>/health, .../parameters/<name>/value")
    home_assistant: HomeAssistantConfig = Field(default_factory=HomeAssistantConfig)

    @field_validator("topic_prefix")
    @classmethod
    def _prefix(cls, value: str) -> str:
        return check_topic(value, "topic_prefix")


# -- what is published ------------------------------------------------------------------------
