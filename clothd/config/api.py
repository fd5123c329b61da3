"""The API's sections of the configuration: the HTTP API (`api:`) and the OPC UA server (`opcua:`), and
what both ask of an address: off loopback, a token and a secure channel."""

from __future__ import annotations

import ipaddress
from pathlib import Path
from typing import Literal
from urllib.parse import urlsplit

from pydantic import Field, field_validator, model_validator

from clothd.config.strict import Strict


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


class ApiConfig(Strict):
    host: str = Field("127.0.0.1", min_length=1, max_length=255)
    port: int = Field(8080, ge=1, le=65535)
    token: str | None = Field(None, min_length=16, max_length=256, description="required off loopback")
    view_fps: float = Field(10.0, gt=0, le=30, description="the annotated MJPEG view's rate")
    allowed_hosts: tuple[str, ...] = Field(
        (), max_length=32, description="host names the API answers to besides 127.0.0.1, localhost and [::1]"
    )
    allowed_origins: tuple[str, ...] = Field(
        (),
        max_length=32,
        description="web origins (scheme://host[:port]) that may change things, besides its own",
    )
    max_body_bytes: int = Field(
        4096, ge=256, le=1_000_000, description="a larger request body is refused (413)"
    )
    max_connections: int = Field(
        128, ge=8, le=2048, description="open HTTP connections; one more evicts the oldest idle one"
    )
    request_timeout_s: float = Field(
        5.0, gt=0, le=120, description="a request must arrive whole this soon after its connection opens"
    )
    max_streams: int = Field(
        32, ge=1, le=512, description="WebSockets and MJPEG views open at once, apart from max_connections"
    )
    stall_timeout_s: float = Field(
        5.0, gt=0, le=120, description="a client that reads nothing this long while data waits is dropped"
    )

    @model_validator(mode="after")
    def _token_off_loopback(self) -> ApiConfig:
        """Off loopback, the API needs a token: refuse to start without one."""
        if not is_loopback(self.host) and self.token is None:
            raise ValueError(
                f"api.host: {self.host} is reachable from other machines; set api.token (16+ characters) "
                "so that changes need Authorization: Bearer <token>, or bind to 127.0.0.1"
            )
        return self


OPCUA_SIGN_AND_ENCRYPT = "Basic256Sha256_SignAndEncrypt"


def opcua_host_port(endpoint: str) -> tuple[str, int]:
    """The host and port an opc.tcp:// endpoint binds to (4840, OPC UA's registered port, when none)."""
    url = urlsplit(endpoint)
    return url.hostname or "", url.port or 4840


class OpcUaConfig(Strict):
    """The OPC UA server (docs/opcua.md). Loopback: anonymous reads, no security policy needed. Anywhere
    else: Basic256Sha256 SignAndEncrypt only, with a certificate made on first start in `cert_dir`."""

    enabled: bool = True
    endpoint: str = Field("opc.tcp://127.0.0.1:4840/clothd/", min_length=1, max_length=255)
    security_policies: tuple[Literal["None", "Basic256Sha256_SignAndEncrypt"], ...] = Field(
        ("None",), min_length=1, max_length=2, description="offered to clients; None only on loopback"
    )
    cert_dir: Path = Field(
        Path("opcua"), description="server key and certificate; relative: to the state directory (systemd)"
    )
    publish_hz: float = Field(10.0, gt=0, le=10, description="how often the variables follow the status")
    max_message_bytes: int = Field(
        262_144,
        ge=8192,
        le=16_777_216,
        description="a larger request, or a chunk over 64 KiB, closes its peer",
    )
    max_anonymous_sessions: int = Field(32, ge=0, le=1000, description="activated anonymous sessions at once")
    max_user_sessions: int = Field(8, ge=1, le=100, description="activated sessions of user clothd, apart")
    max_pending_connections: int = Field(
        32, ge=1, le=1000, description="connections with no session yet; one more closes the oldest"
    )
    activation_timeout_s: float = Field(
        5.0, gt=0, le=60, description="a connection with no activated session after this is closed"
    )

    @field_validator("endpoint")
    @classmethod
    def _opc_tcp_url(cls, endpoint: str) -> str:
        try:
            host, _ = opcua_host_port(endpoint)  # a port that is no number, or out of range, raises
        except ValueError as err:
            raise ValueError(f"{endpoint!r} is not a URL: {err}") from None
        if urlsplit(endpoint).scheme != "opc.tcp" or not host:
            raise ValueError(f"{endpoint!r}: an endpoint is opc.tcp://HOST:PORT/PATH")
        return endpoint

    @model_validator(mode="after")
    def _secure_off_loopback(self) -> OpcUaConfig:
        """Off loopback, the None policy (plain text, no server identity) is refused at start."""
        host, _ = opcua_host_port(self.endpoint)
        if not is_loopback(host) and self.security_policies != (OPCUA_SIGN_AND_ENCRYPT,):
            raise ValueError(
                f"opcua.endpoint: {self.endpoint} is reachable from other machines; set "
                f"opcua.security_policies to [{OPCUA_SIGN_AND_ENCRYPT}] (no None policy off loopback), "
                "or bind to 127.0.0.1"
            )
        return self
