"""``[outputs.opcua]``: the OPC UA output's table (:class:`OpcUaConfig`)."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Literal, Self

from pydantic import Field, StrictFloat, StrictInt, field_validator, model_validator

from twinwatch.sinks.base import SinkConfig

__all__ = ["SECURITY", "OpcUaConfig"]

SECURITY = Literal["None", "Basic256Sha256_Sign", "Basic256Sha256_SignAndEncrypt"]
_ENDPOINT_RE = re.compile(r"^opc\.tcp://(?P<host>\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9][A-Za-z0-9.-]*)"
                          r":(?P<port>[0-9]{1,5})(?P<path>/[^\s]*)?$")


class OpcUaConfig(SinkConfig):
    """``[outputs.opcua]``: the OPC UA server output (docs/opcua-output.md has an example)."""

    endpoint: str = Field("opc.tcp://127.0.0.1:4840",
                          description="opc.tcp://host:port the server listens on")
    namespace: str = Field("urn:twinwatch:health", min_length=1,
                           description="the namespace URI of the machines' nodes")
    security: list[SECURITY] = Field(
        default_factory=lambda: list[SECURITY](["None"]), min_length=1,
        description="endpoints offered: None, Basic256Sha256_Sign, "
        "Basic256Sha256_SignAndEncrypt (the last two need certificate and private_key)")
    certificate: str | None = Field(None, description="the server's certificate (DER or PEM)")
    private_key: str | None = Field(None, description="its private key (PEM; a secret: 0640)")
    trusted_clients: list[str] = Field(
        default_factory=list, description="client certificates (DER or PEM) allowed on the "
        "signed endpoints; empty: any client certificate")
    history: StrictInt = Field(0, ge=0, le=100_000,
                               description="windows of each parameter's Value kept for "
                               "HistoryRead (in memory); 0: no history")
    stale_after: StrictFloat = Field(
        30.0, gt=0, allow_inf_nan=False,
        description="s without a window before DeviceHealth says CHECK_FUNCTION (source lost)")

    @field_validator("endpoint")
    @classmethod
    def _endpoint(cls, value: str) -> str:
        m = _ENDPOINT_RE.match(value)
        if m is None:
            raise ValueError(f"endpoint {value!r} is not of the form opc.tcp://host:port, "
                             f"e.g. 'opc.tcp://127.0.0.1:4840'")
        if not 1 <= int(m["port"]) <= 65535:
            raise ValueError(f"endpoint {value!r}: port {m['port']} is not in 1..65535")
        return value

    @model_validator(mode="after")
    def _check(self) -> Self:
        secure = [s for s in self.security if s != "None"]
        if secure and not (self.certificate and self.private_key):
            raise ValueError(f"security {secure[0]!r} needs certificate and private_key (the "
                             f"server's certificate and its key), or security = ['None']")
        if len(set(self.security)) != len(self.security):
            raise ValueError("security lists an endpoint twice")
        return self

    def host_port(self) -> tuple[str, int]:
        """The endpoint's host and port."""
        m = _ENDPOINT_RE.match(self.endpoint)
        assert m is not None
        return m["host"].strip("[]"), int(m["port"])

    def input_files(self) -> dict[str, str]:
        """The certificate, the private key and the trusted client certificates."""
        out = {k: v for k in ("certificate", "private_key") if (v := getattr(self, k))}
        out.update({f"trusted_clients.{i}": p for i, p in enumerate(self.trusted_clients)})
        return out

    def secret_input_files(self) -> dict[str, str]:
        """The private key: refused when others can read it."""
        return {"private_key": self.private_key} if self.private_key else {}

    def exclusive_resources(self, cwd: Path) -> set[str]:
        """The port the server listens on."""
        host, port = self.host_port()
        return {f"opcua:{host}:{port}"}

    def server_key(self) -> str:
        """What one shared server is made of: everything but ``enabled`` and ``stale_after``
        (machines whose tables differ only in those share it)."""
        return "opcua:" + json.dumps(self.model_dump(exclude={"enabled", "stale_after"}),
                                     sort_keys=True)
