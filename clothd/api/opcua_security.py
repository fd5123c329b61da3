"""Who may do what on the OPC UA server, and its certificate.

- On loopback, reads (browse, read, subscribe) are anonymous. Off loopback nobody is anonymous: the
  configuration then needs api.token (clothd/config/).
- With api.token set, method calls need user `clothd` with the token as password; without one (loopback
  only) anyone who can reach loopback may call, as with the REST API (docs/api.md says why).
- Off loopback the only policy is Basic256Sha256 SignAndEncrypt, with a self-signed certificate made on
  first start in opcua.cert_dir (the state directory under systemd) and kept there. A None channel that
  is not offered serves discovery only (DiscoveryOnly: asyncua alone would serve it everything).
"""

from __future__ import annotations

import hmac
import socket
from pathlib import Path
from typing import Any

from asyncua import ua
from asyncua.crypto.cert_gen import setup_self_signed_certificate
from asyncua.crypto.permission_rules import USER_TYPES, SimpleRoleRuleset, User, UserRole
from asyncua.crypto.security_policies import SecurityPolicyFactory, SecurityPolicyNone
from asyncua.server.user_managers import UserManager
from cryptography.x509.oid import ExtendedKeyUsageOID

from clothd.api.opcua_limits import SessionSlots

USER_NAME = "clothd"
CALL = ua.NodeId(ua.Int32(ua.ObjectIds.CallRequest_Encoding_DefaultBinary))
KEY_FILE = "server-key.pem"
CERT_FILE = "server-cert.der"


class TokenUsers(UserManager):
    """asyncua's user manager: `clothd` with the token is a user; no name is anonymous, where allowed.
    Each class of session is admitted only while it has a free slot (SessionSlots)."""

    def __init__(self, token: str | None, anonymous: bool, slots: SessionSlots) -> None:
        self.token = token
        self.anonymous = anonymous
        self.slots = slots

    def get_user(
        self, iserver: Any, username: str | None = None, password: str | None = None, certificate: Any = None
    ) -> User | None:
        user = self._identify(username, password)
        if user is not None:
            self.slots.admit(user.role)
        return user

    def _identify(self, username: str | None, password: str | None) -> User | None:
        if username is None and password is None:
            return User(role=UserRole.Anonymous) if self.anonymous else None
        if self.token is None or username != USER_NAME or password is None:
            return None
        # asyncua hands over a str (it decodes the token); bytes would be taken as they are
        given = password.encode() if isinstance(password, str) else bytes(password)
        if not hmac.compare_digest(given, self.token.encode()):
            return None
        return User(role=UserRole.User, name=USER_NAME)


class CellRules(SimpleRoleRuleset):
    """Users may do every session service; anonymous sessions all but Call when a token is set."""

    def __init__(self, token_set: bool) -> None:  # SimpleRoleRuleset's own table is not used
        services = {ua.NodeId(ua.Int32(t)) for t in USER_TYPES}
        self.allowed = {
            UserRole.User: services,
            UserRole.Anonymous: services - {CALL} if token_set else services,
        }

    def check_validity(self, user: User, action_type_id: ua.NodeId, body: Any) -> bool:
        return action_type_id in self.allowed.get(user.role, set())


class DiscoveryOnly(SecurityPolicyFactory):
    """Put after the offered policies: a channel asking for a policy none of them matched gets the None
    policy for discovery (GetEndpoints, FindServers: how a client learns the server's certificate, Part 4
    5.4) and is refused everything a session does.

    asyncua 2.1 opens each connection with the None policy and keeps it when a client asks for None and
    no offered policy matches (SecureConnection.select_policy), with no permission ruleset at all: without
    this, a client could read and call in plain text on a server that offers only SignAndEncrypt."""

    def __init__(self) -> None:
        super().__init__(SecurityPolicyNone, ua.MessageSecurityMode.None_, permission_ruleset=_NOTHING)

    def matches(self, uri: str, mode: ua.MessageSecurityMode | None = None) -> bool:
        return uri == SecurityPolicyNone.URI


class _Nothing(SimpleRoleRuleset):
    """No session service for anyone (discovery is never checked against a ruleset)."""

    def check_validity(self, user: User, action_type_id: ua.NodeId, body: Any) -> bool:
        return False


_NOTHING = _Nothing()


async def server_certificate(cert_dir: Path, app_uri: str) -> tuple[Path, Path]:
    """(certificate, private key) in cert_dir: made on first start, made again when invalid or expired
    (asyncua's helper checks it against app_uri and this host's name). The directory is private: it holds
    the key."""
    cert_dir.mkdir(mode=0o700, parents=True, exist_ok=True)
    cert, key = cert_dir / CERT_FILE, cert_dir / KEY_FILE
    await setup_self_signed_certificate(
        key,
        cert,
        app_uri,
        socket.gethostname(),
        [ExtendedKeyUsageOID.SERVER_AUTH],
        {"commonName": "clothd", "organizationName": "clothd"},
    )
    key.chmod(0o600)
    return cert, key
